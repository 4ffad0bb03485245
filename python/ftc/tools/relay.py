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

from ftc.common.cli import OneLineParser, at_least, between, checked
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


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="python -m ftc.relay", description=__doc__.split("\n\n")[0])
    parser.add_argument("--lcm-url", type=checked(str, nonempty=True), default=DEFAULT_LCM_URL,
                        help="LCM URL (ttl=0)")
    parser.add_argument("--client-prefix", type=checked(str, nonempty=True), required=True,
                        help="prefix the controller uses")
    parser.add_argument("--plant-prefix", type=checked(str, nonempty=True), required=True,
                        help="prefix the plant uses")
    # a rate of 1 would forward nothing (loss) or loop forever (duplicate)
    parser.add_argument("--loss", type=checked(float, between(0.0, 1.0)), default=0.05,
                        help="drop probability per message")
    parser.add_argument("--duplicate", type=checked(float, between(0.0, 1.0)), default=0.0,
                        help="probability of sending a forwarded message twice")
    parser.add_argument("--seed", type=checked(int, at_least(0, 2**63 - 1)), default=0,
                        help="seed of the fault draws")
    return parser


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The options, all checked before the relay opens LCM (exit 2, one line)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    for name in ("loss", "duplicate"):
        if getattr(args, name) >= 1.0:
            parser.error(f"--{name} must be in [0, 1), got {getattr(args, name)}")
    if args.client_prefix == args.plant_prefix:
        parser.error("--client-prefix and --plant-prefix must differ (the relay would loop)")
    try:
        check_loopback_url(args.lcm_url)
    except ValueError as e:
        parser.error(f"--lcm-url: {e}")
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    relay = LossyRelay(args.lcm_url, args.client_prefix, args.plant_prefix,
                       loss=args.loss, duplicate=args.duplicate, seed=args.seed)
    stop = {"flag": False}
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.__setitem__("flag", True))
    print("ready", flush=True)
    relay.run(lambda: stop["flag"])
    print(json.dumps(relay.counts), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
