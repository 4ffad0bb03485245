"""A lossy LCM relay for fault injection: forwards a controller's messages to
a plant and the plant's answers back, dropping and duplicating messages at set
rates. The controller talks to ``<client-prefix>*``, the plant listens on
``<plant-prefix>*``; neither knows the relay is there.

    python -m ftc.relay --lcm-url 'udpm://239.255.76.67:7700?ttl=0' \\
        --client-prefix CTRL_ --plant-prefix PLANT_ --loss 0.05 --duplicate 0.02

On SIGINT/SIGTERM it prints the counts (forwarded, dropped, duplicated) as one
JSON line on stdout and exits 0.
"""

from __future__ import annotations

import argparse
import json
import random
import signal
import sys
from typing import Callable

from ftc.plant import DEFAULT_LCM_URL, check_loopback_url

# channel suffix -> direction: True from the client to the plant
SUFFIXES = {"COMMAND": True, "CONTROL": True, "STATE": False}


class LossyRelay:
    """Forwards between two channel prefixes on one LCM bus with injected faults."""

    def __init__(self, lcm_url: str, client_prefix: str, plant_prefix: str, *, loss: float,
                 duplicate: float, seed: int) -> None:
        import lcm

        if client_prefix == plant_prefix:
            raise ValueError("client and plant prefixes must differ (the relay would loop)")
        check_loopback_url(lcm_url)
        self._lc = lcm.LCM(lcm_url)
        self._rng = random.Random(seed)
        self.loss, self.duplicate = loss, duplicate
        self.counts = {"forwarded": 0, "dropped": 0, "duplicated": 0}
        for suffix, to_plant in SUFFIXES.items():
            src, dst = ((client_prefix, plant_prefix) if to_plant
                        else (plant_prefix, client_prefix))
            self._lc.subscribe(src + suffix, self._forwarder(dst + suffix))

    def _forwarder(self, destination: str) -> Callable[[str, bytes], None]:
        def forward(channel: str, data: bytes) -> None:
            if self._rng.random() < self.loss:
                self.counts["dropped"] += 1
                return
            self._lc.publish(destination, data)
            self.counts["forwarded"] += 1
            if self._rng.random() < self.duplicate:
                self._lc.publish(destination, data)
                self.counts["duplicated"] += 1
        return forward

    def run(self, should_stop: Callable[[], bool]) -> None:
        while not should_stop():
            try:
                self._lc.handle_timeout(100)
            except OSError:
                if not should_stop():  # a signal interrupting the wait is a stop
                    raise


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m ftc.relay",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--lcm-url", default=DEFAULT_LCM_URL, help="LCM URL (ttl=0)")
    parser.add_argument("--client-prefix", required=True, help="prefix the controller uses")
    parser.add_argument("--plant-prefix", required=True, help="prefix the plant uses")
    parser.add_argument("--loss", type=float, default=0.05, help="drop probability per message")
    parser.add_argument("--duplicate", type=float, default=0.0,
                        help="probability of sending a forwarded message twice")
    parser.add_argument("--seed", type=int, default=0, help="seed of the fault draws")
    args = parser.parse_args(argv)
    for name in ("loss", "duplicate"):
        value = getattr(args, name)
        if not 0.0 <= value < 1.0:
            parser.error(f"--{name} must be in [0, 1), got {value}")
    try:
        relay = LossyRelay(args.lcm_url, args.client_prefix, args.plant_prefix,
                           loss=args.loss, duplicate=args.duplicate, seed=args.seed)
    except ValueError as e:
        parser.error(str(e))
    stop = {"flag": False}
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.__setitem__("flag", True))
    print("ready", flush=True)
    relay.run(lambda: stop["flag"])
    print(json.dumps(relay.counts), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
