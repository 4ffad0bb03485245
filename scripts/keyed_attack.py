#!/usr/bin/env python3
"""Real-time runs with a bus key, undisturbed and under a neighbour without the
key (docs/deploy.md, "The bus"): does the neighbour change the results, and do
the refused counts equal what it sent?

Each run: a real-time plant (single fault, --rate RATE, --key-file) and
``ftc.controller --attach --key-file --method random --seed S`` (valves drawn
per step from the seed: the results vary with it), one interval of --steps
steps. Under attack, once the run's session is open, a process without the key
that reads the session and the seqs off the bus sends every --every seconds:
an unsigned valve command in the session (all valves open, the next seq),
unsigned START, RESET and SHUTDOWN in the session, a signed command of the
controller's replayed, a copy of it with a valve flipped (tampered), a forged
state of the session (unsigned, the next seq) and a signed state of the plant's
replayed to the controller.

    .venv/bin/python scripts/keyed_attack.py [--seeds 0 1 2] [--rate 50] [--steps 256]
        [--results docs/results/keyed_attack.csv]

Per run it prints the reward per step, the deadline misses and what was sent
against what was refused: the plant's own counts (bad_signature: the unsigned
and tampered messages; replayed), the controller's (refused_bad_signature: the
forged states; refused_replay: the replayed states). At the end: each attacked
run's reward against its undisturbed twin, and the seeds' own spread (max -
min of the undisturbed runs): the neighbour changes nothing when every
difference is below that spread. Exit 1 if a count differs or a difference is
not below the spread.
"""

from __future__ import annotations

import argparse
import csv
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "python"))
sys.path.insert(0, str(REPO / "scripts"))

import lcm  # noqa: E402

from ftc.common.build_info import git_revision, plant_binary  # noqa: E402
from ftc.plant import private_lcm_url, private_prefix  # noqa: E402
from ftc.plant.signing import TRAILER_BYTES, new_key  # noqa: E402
from ftc.plant.wire import decode_state  # noqa: E402
from ftc.plant_control_t import plant_control_t  # noqa: E402
from ftc.valve_command_t import valve_command_t  # noqa: E402

SENT = ("unsigned", "tampered", "replayed commands", "forged states", "replayed states")


class Neighbour:
    """Listens on the run's channels (every message is readable: signing is not
    encryption) and, once ``attack`` is set, sends the module doc's messages."""

    def __init__(self, url: str, prefix: str) -> None:
        self.lc, self.prefix = lcm.LCM(url), prefix
        self.states: list = []  # (decoded payload, the signed bytes)
        self.commands: list[bytes] = []  # the controller's, signed
        self.sent = dict.fromkeys(SENT, 0)
        self.lc.subscribe(prefix + "STATE", self._on_state)
        self.lc.subscribe(prefix + "COMMAND", lambda _c, d: self.commands.append(d))

    def _on_state(self, _channel: str, data: bytes) -> None:
        msg, _ = decode_state(data[:-TRAILER_BYTES])
        if msg is not None:  # the plant's (the neighbour's own forgeries carry no trailer)
            self.states.append((msg, data))

    def spin(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.lc.handle_timeout(20)

    def session_open(self, run: subprocess.Popen, timeout: float = 60) -> bool:
        """Wait for a state of the run's own session answering its commands."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and run.poll() is None:
            if any(s.session != 0 and s.command_seq > 10 and not s.watchdog_tripped
                   for s, _ in self.states[-5:]):
                return True
            self.lc.handle_timeout(50)
        return False

    def attack_once(self) -> None:
        p, last = self.prefix, self.states[-1][0]
        session, seq = last.session, last.command_seq
        cmd = valve_command_t()
        cmd.session, cmd.seq, cmd.num_valves, cmd.valve = session, seq + 1, 6, [1] * 6
        cmd.utime = time.time_ns() // 1000
        self.lc.publish(p + "COMMAND", cmd.encode())
        for command in (plant_control_t.START, plant_control_t.RESET, plant_control_t.SHUTDOWN):
            msg = plant_control_t()
            msg.session, msg.seq, msg.command = session, seq + 2, command
            self.lc.publish(p + "CONTROL", msg.encode())
        self.sent["unsigned"] += 4
        own = self.commands[-1]
        self.lc.publish(p + "COMMAND", own)
        self.sent["replayed commands"] += 1
        tampered = bytearray(own)
        tampered[len(own) - TRAILER_BYTES - 1] ^= 1  # the last valve
        self.lc.publish(p + "COMMAND", bytes(tampered))
        self.sent["tampered"] += 1
        forged, _ = decode_state(self.states[-1][1][:-TRAILER_BYTES])  # a copy to alter
        forged.seq += 1
        self.lc.publish(p + "STATE", forged.encode())
        self.sent["forged states"] += 1
        self.lc.publish(p + "STATE", self.states[-2][1])
        self.sent["replayed states"] += 1


def one_run(seed: int, attack: bool, rate: float, steps: int, every: float, tmp: Path) -> dict:
    url, prefix = private_lcm_url(), private_prefix()
    key_file = tmp / "bus.key"
    key_file.write_text(new_key().hex())
    key_file.chmod(0o600)
    plant = subprocess.Popen([str(plant_binary()), "--lcm-url", url, "--prefix", prefix,
                              "--scenario", str(REPO / "scenarios" / "single.toml"),
                              "--key-file", str(key_file), "--steps-per-interval", str(steps),
                              "--mode", "realtime", "--rate", f"{rate:g}"],
                             stderr=subprocess.DEVNULL)
    out = tmp / f"{'attacked' if attack else 'quiet'}-s{seed}"
    neighbour = Neighbour(url, prefix)
    run = subprocess.Popen(
        [sys.executable, "-m", "ftc.controller", "--attach", "--key-file", str(key_file),
         "--method", "random", "--seed", str(seed), "--lcm-url", url, "--prefix", prefix,
         "--intervals", "1", "--steps-per-interval", str(steps), "--quiet", "--out", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO / "python"), "OMP_NUM_THREADS": "1"})
    err = ""
    try:
        if not neighbour.session_open(run):
            raise SystemExit(f"keyed_attack: seed {seed}: the run's session did not open: "
                             f"{run.communicate()[1][-1000:]}")
        stop = time.monotonic() + 0.6 * steps / rate  # attack within the interval
        while attack and time.monotonic() < stop and run.poll() is None:
            neighbour.attack_once()
            neighbour.spin(every)
        _, err = run.communicate(timeout=4 * steps / rate + 120)
        while neighbour.lc.handle_timeout(0) > 0:  # LCM's queue (30) holds old states
            pass
        neighbour.spin(0.5)  # the plant's newest state: its counters after the run
    finally:
        run.kill()
        plant.kill()
        plant.wait()
    if run.returncode != 0:
        raise SystemExit(f"keyed_attack: seed {seed}: the run exited {run.returncode}: "
                         f"{err.strip()[-1000:]}")
    with open(out / "metrics.csv", newline="") as f:
        (row,) = list(csv.DictReader(f))
    last = neighbour.states[-1][0]
    sent = neighbour.sent
    counts = {"plant_bad_signature": int(last.bad_signature),
              "plant_replayed": int(last.replayed),
              "link_bad_signature": int(row["refused_bad_signature"]),
              "link_replay": int(row["refused_replay"])}
    expected = {"plant_bad_signature": sent["unsigned"] + sent["tampered"],
                "plant_replayed": sent["replayed commands"],
                "link_bad_signature": sent["forged states"],
                "link_replay": sent["replayed states"]}
    return {"seed": str(seed), "attacked": "yes" if attack else "no",
            "reward_per_step": row["reward_per_step"],
            "deadline_misses": row["deadline_misses"],
            "foreign_commands": row["foreign_commands"],
            **{f"sent_{k.replace(' ', '_')}": str(v) for k, v in sent.items()},
            **{k: str(v) for k, v in counts.items()},
            "counts_equal_sent": "yes" if counts == expected else "no"}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--rate", type=float, default=50.0, help="the plant's rate, Hz")
    p.add_argument("--steps", type=int, default=256, help="steps of the one interval")
    p.add_argument("--every", type=float, default=0.2, help="s between two attacks")
    p.add_argument("--results", type=Path, help="write the table as a result file")
    args = p.parse_args(argv)
    if len(args.seeds) < 2:
        p.error("--seeds: at least two (the seeds' spread is the yardstick)")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            for attack in (False, True):
                rows.append(one_run(seed, attack, args.rate, args.steps, args.every, Path(tmp)))
                print(" ".join(f"{k} {v}" for k, v in rows[-1].items()), flush=True)
    quiet = {r["seed"]: float(r["reward_per_step"]) for r in rows if r["attacked"] == "no"}
    spread = max(quiet.values()) - min(quiet.values())
    diffs = {r["seed"]: abs(float(r["reward_per_step"]) - quiet[r["seed"]])
             for r in rows if r["attacked"] == "yes"}
    for r in rows:
        r["difference_to_undisturbed"] = (f"{diffs[r['seed']]:.5f}" if r["attacked"] == "yes"
                                          else "")
        r["seed_spread"] = f"{spread:.5f}"
    counts_ok = all(r["counts_equal_sent"] == "yes" for r in rows)
    within = all(d < spread for d in diffs.values())
    print(f"keyed_attack: largest difference attacked - undisturbed "
          f"{max(diffs.values()):.5f} reward/step, the seeds' spread {spread:.5f}: "
          f"{'within' if within else 'NOT within'}; refused counts "
          f"{'equal' if counts_ok else 'DIFFER FROM'} what was sent")
    if args.results:
        from suite_results import write_result_file

        write_result_file(args.results, (
            f"# what: real-time runs with a bus key (plant and ftc.controller --attach "
            f"--key-file, --method random, single fault, {args.rate:g} Hz, 1 x {args.steps} "
            f"steps), undisturbed and under a neighbour without the key sending every "
            f"{args.every:g} s unsigned commands/START/RESET/SHUTDOWN in the session, replayed "
            f"and tampered commands, forged and replayed states; refused counts: the plant's "
            f"and the controller's\n"
            f"# command: scripts/keyed_attack.py --seeds {' '.join(map(str, args.seeds))} "
            f"--rate {args.rate:g} --steps {args.steps} --every {args.every:g}\n"
            f"# commit: {git_revision()}\n"), rows)
    return 0 if counts_ok and within else 1


if __name__ == "__main__":
    sys.exit(main())
