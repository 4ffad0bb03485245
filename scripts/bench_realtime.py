#!/usr/bin/env python3
"""How fast a plant each controller keeps up with: the plant in real-time
mode at rising rates, driven by

    node   build/policy_node flying a policy (a fresh ActorCritic, seed 0,
           exported as the node reads it) for --steps steps;
    node-student  build/policy_node flying the adaptive student (its history
           window: docs/adaptive.md), exported by ftc.export from --student
           (default: the checkpoint `python -m ftc.experiments.adaptive train`
           cached for its default options), for --steps steps;
    node-signed  the same as node with a bus key (plant and node --key-file): every
           message signed and checked (HMAC-SHA256), for the signing's cost
           side by side with node at the same rates (with both, each rate runs
           --repeats pairs, node and node-signed alternating ABBA, and the
           signing's cost is printed: the median p99 of each, their difference
           against the budget, max(5% of the unsigned p99, 20 us), and the node's
           own time in HMAC per step; --signing-results writes it);
    ppo    python -m ftc.controller --method ppo-offline --realtime RATE, learning
           on: 2 intervals of 256 steps, a PPO update every 128 steps and the
           offline phase (2048 model steps) after each interval, plus the
           evaluation episodes;
    mpc    python -m ftc.mpc --method oracle-mpc --realtime RATE, the same run;
    robust python -m ftc.controller --method ppo-robust --pretrain --offline-steps 0
           --realtime RATE, the same run: PPO updates and the guided fit (DAgger
           with the planner) after each interval, off the control loop.

    .venv/bin/python scripts/bench_realtime.py --controllers node-student --rates 100 \
        --steps 5000 --results docs/results/node_student.csv
    .venv/bin/python scripts/bench_realtime.py [--controllers node ppo mpc] [--steps 5000]
        [--rates 100 200 500 1000 2000] [--python-rates 20 50 100 200]
        [--results docs/results/realtime.csv] [--figure docs/figures/realtime_latency.png]

Every plant is on a private loopback port (single fault, --watchdog 1). A
deadline miss is a plant step taken before the command answering the state
before it; the latency runs from the state's arrival to the command's send.
The node prints both; a Python run's metrics.csv has them per interval
(deadline_misses summed, p50 the median of the intervals', p99 and max the
worst interval's). The highest rate with fewer than 0.1% misses is reported
per controller. With --results the table is written as a result file
(docs/results/), with --figure a histogram of the node's latencies at its
lowest rate.
"""

from __future__ import annotations

import argparse
import csv
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "python"))
sys.path.insert(0, str(REPO / "scripts"))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from ftc.common.build_info import git_revision, plant_binary, policy_node_binary  # noqa: E402
from ftc.plant.signing import new_key  # noqa: E402
from ftc.learning.ppo import ActorCritic  # noqa: E402
from ftc.plant import private_lcm_url, private_prefix  # noqa: E402
from ftc.tools import policy_weights  # noqa: E402

SUMMARY = re.compile(r"steps (\d+) deadline_misses (\d+) latency_p50_us (\d+) "
                     r"latency_p99_us (\d+) latency_max_us (\d+) auth_us_per_step ([\d.]+)")
SIGNING_BUDGET = (0.05, 20.0)  # signing may cost the node 5% of its p99 latency, or 20 us
MISS_LIMIT = 0.001  # the aim: fewer than 0.1% of the steps missed
DEFAULT_CACHE = "~/.cache/ftc/adaptive"  # where `python -m ftc.experiments.adaptive train` caches


def run_rate(weights: Path, rate: float, steps: int, log: Path,
             key_file: Path | None = None, name: str = "node", fifo: int = 0,
             pin: tuple[int, int] | None = None) -> dict:
    """One node run; with ``fifo`` the plant and the node under SCHED_FIFO at that
    priority (chrt), as a real-time deployment schedules its control loop; with
    ``pin`` (plant CPU, node CPU) each held on its own CPU (taskset), as a
    deployment that keeps its control loop's core to itself."""
    url, prefix = private_lcm_url(), private_prefix()
    keyed = ["--key-file", str(key_file)] if key_file else []
    chrt = ["chrt", "-f", str(fifo)] if fifo else []
    plant_cpu = ["taskset", "-c", str(pin[0])] if pin else []
    node_cpu = ["taskset", "-c", str(pin[1])] if pin else []
    plant = subprocess.Popen([*plant_cpu, *chrt, str(plant_binary()),
                              "--scenario", str(REPO / "scenarios" / "single.toml"),
                              "--mode", "realtime", "--rate", str(rate), "--watchdog", "1",
                              "--lcm-url", url, "--prefix", prefix, *keyed],
                             stderr=subprocess.DEVNULL)
    try:
        out = subprocess.run([*node_cpu, *chrt, str(policy_node_binary()),
                              "--policy", str(weights), "--lcm-url", url, "--prefix", prefix,
                              "--steps", str(steps), "--latency-log", str(log), *keyed],
                             capture_output=True, text=True, timeout=steps / rate + 60)
    finally:
        plant.kill()
        plant.wait()
    m = SUMMARY.search(out.stdout)
    if out.returncode or not m:
        raise SystemExit(f"bench_realtime: the node failed at {rate} Hz: {out.stderr.strip()}")
    n, misses, p50, p99, worst = map(int, m.groups()[:5])
    for line in out.stderr.splitlines():  # the node logs its first misses: which steps
        if "deadline miss" in line:
            print(f"bench_realtime: {name} at {rate:g} Hz: {line}", file=sys.stderr)
    row = _row(name, rate, n, misses, p50, p99, worst,
               scheduler=(f"fifo {fifo}" if fifo else "other")
               + (f", pinned {pin[0]}/{pin[1]}" if pin else ""))
    row["auth_us_per_step"] = m.group(6)
    return row


def _row(controller: str, rate: float, n: int, misses: int, p50: float, p99: float,
         worst: float, scheduler: str = "other") -> dict:
    return {"controller": controller, "scheduler": scheduler, "rate_hz": f"{rate:g}",
            "steps": str(n),
            "deadline_misses": str(misses), "miss_fraction": f"{misses / n:.4f}",
            "latency_p50_us": f"{p50:.0f}", "latency_p99_us": f"{p99:.0f}",
            "latency_max_us": f"{worst:.0f}",
            "keeps_up": "yes" if misses / n < MISS_LIMIT else "no", "auth_us_per_step": ""}


PYTHON_RUNS = {  # controller -> the run (2 intervals of 256 steps, the plant's rate added)
    "ppo": ["ftc.controller", "--method", "ppo-offline", "--update-every", "128"],
    "mpc": ["ftc.mpc", "--method", "oracle-mpc"],
    "robust": ["ftc.controller", "--method", "ppo-robust", "--pretrain", "--offline-steps", "0",
               "--update-every", "128"],
}


def run_python(controller: str, rate: float, out: Path) -> dict:
    """One real-time run of a Python controller; its deadlines from metrics.csv."""
    cmd = [sys.executable, "-m", *PYTHON_RUNS[controller], "--realtime", f"{rate:g}",
           "--intervals", "2", "--steps-per-interval", "256", "--quiet", "--out", str(out)]
    env = {**os.environ, "PYTHONPATH": str(REPO / "python"), "OMP_NUM_THREADS": "1"}
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=REPO,
                          timeout=4 * 512 / rate + 300)
    if done.returncode:
        raise SystemExit(f"bench_realtime: {controller} failed at {rate:g} Hz: "
                         f"{done.stderr.strip()[-2000:]}")
    with open(out / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    n = sum(256 + int(r["eval_steps"]) for r in rows)
    p50 = float(np.median([float(r["latency_p50_ms"]) for r in rows]))
    p99 = max(float(r["latency_p99_ms"]) for r in rows)
    worst = max(float(r["latency_max_ms"]) for r in rows)
    return _row(controller, rate, n, sum(int(r["deadline_misses"]) for r in rows),
                1000 * p50, 1000 * p99, 1000 * worst)


def _node_runs(controllers: list[str], rates: list[float], repeats: int) -> list:
    """(controller, rate) in the order to run: per rate, ``repeats`` rounds of
    the node controllers, each round in the reverse order of the one before
    (ABBA for a pair), so that a change of the machine's load falls on all
    alike."""
    nodes = list(dict.fromkeys(c for c in controllers if c.startswith("node")))
    order = []
    for rate in sorted(rates):
        for k in range(repeats):
            order += [(c, rate) for c in (nodes if k % 2 == 0 else nodes[::-1])]
    return order


def pin_cpus() -> tuple[int, int]:
    """(plant CPU, node CPU) for --pin: the first two this process may run on."""
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        raise SystemExit(f"bench_realtime: --pin needs two CPUs; this process may use {cpus}")
    return cpus[0], cpus[1]


def signing_cost(rows: list[dict]) -> list[dict]:
    """Per rate with both node and node-signed rows: the median p99 latency of
    each, the difference, the budget (max(5% of the unsigned p99, 20 us)) and
    whether it is met, and the signed node's median time in HMAC per step."""
    out = []
    rows = [r for r in rows if r["scheduler"] == "other"]
    for rate in dict.fromkeys(r["rate_hz"] for r in rows):
        plain = [float(r["latency_p99_us"]) for r in rows
                 if r["rate_hz"] == rate and r["controller"] == "node"]
        signed = [float(r["latency_p99_us"]) for r in rows
                  if r["rate_hz"] == rate and r["controller"] == "node-signed"]
        if not plain or not signed:
            continue
        auth = [float(r["auth_us_per_step"]) for r in rows
                if r["rate_hz"] == rate and r["controller"] == "node-signed"]
        p_plain, p_signed = float(np.median(plain)), float(np.median(signed))
        budget = max(SIGNING_BUDGET[0] * p_plain, SIGNING_BUDGET[1])
        out.append({"rate_hz": rate, "pairs": str(min(len(plain), len(signed))),
                    "p99_unsigned_us": f"{p_plain:.0f}", "p99_signed_us": f"{p_signed:.0f}",
                    "p99_unsigned_runs": " ".join(f"{v:.0f}" for v in plain),
                    "p99_signed_runs": " ".join(f"{v:.0f}" for v in signed),
                    "difference_us": f"{p_signed - p_plain:.0f}",
                    "budget_us": f"{budget:.0f}",
                    "within_budget": "yes" if p_signed - p_plain <= budget else "no",
                    "hmac_us_per_step": f"{float(np.median(auth)):.2f}"})
    return out


def student_weights(student: Path | None, out: Path) -> str:
    """Exports the adaptive student (``student``, or the cached checkpoint of
    the default training options) to ``out`` with ftc.export; returns the
    checkpoint's path. Exits naming the train command when there is none."""
    from ftc.control.agents.learned.adaptive_policy import TRAIN_COMMAND, default_checkpoint
    from ftc.tools.export import main as export

    path = student or default_checkpoint(DEFAULT_CACHE)
    if not path.is_file():
        raise SystemExit(f"bench_realtime: no student checkpoint at {path}; build it with "
                         f"`{TRAIN_COMMAND}` or give --student")
    if export([str(path), "--weights", str(out)]) != 0:
        raise SystemExit(f"bench_realtime: ftc.export could not export {path}")
    return str(path)


def student_shape(weights: Path) -> str:
    """'a window of W steps, A-B-...' of an exported student."""
    policy = policy_weights.read_policy(weights)
    return f"a window of {policy.window} steps, {'-'.join(map(str, policy.widths))}"


def student_name(student: Path | None) -> str:
    """How the result file names the student flown: the given file, or the cache's."""
    # (not the cache's file name: its hex key reads as a commit hash in the docs)
    return str(student) if student is not None else "the cached default checkpoint"


def measure(controllers: list[str], steps: int, rates: list[float],
            python_rates: list[float], echo: bool = False,
            repeats: int = 1, student: Path | None = None,
            fifo: int = 0, pin: tuple[int, int] | None = None) -> tuple[list[dict], Any]:
    """Every controller at every rate: the table's rows, and the node's latencies
    at its lowest rate with that row (or None); with ``pin`` (plant CPU, node
    CPU) each node run also pinned, beside the unpinned one."""
    torch.manual_seed(0)
    rows, first_log = [], None
    with tempfile.TemporaryDirectory() as tmp:
        weights = Path(tmp) / "policy.txt"
        policy_weights.write_weights(weights, *policy_weights.actor_layers(ActorCritic()))
        student_file = Path(tmp) / "student.txt"
        if "node-student" in controllers:
            print(f"bench_realtime: node-student flies {student_weights(student, student_file)}",
                  flush=True)
        key_file = Path(tmp) / "bus.key"
        key_file.write_text(new_key().hex())
        key_file.chmod(0o600)
        # each scheduler, and each placement, beside the other
        ways = [(f, where) for where in ((None, pin) if pin else (None,))
                for f in ((0, fifo) if fifo else (0,))]
        runs = [(c, rate, f, where) for c, rate in _node_runs(controllers, rates, repeats)
                for f, where in ways]
        runs += [(c, rate, 0, None) for c in controllers if not c.startswith("node")
                 for rate in sorted(python_rates)]
        for controller, rate, f, where in runs:
            if controller.startswith("node"):
                log = Path(tmp) / f"latency-{controller}-{rate:g}.txt"
                rows.append(run_rate(student_file if controller == "node-student" else weights,
                                     rate, steps, log,
                                     key_file if controller == "node-signed" else None,
                                     name=controller, fifo=f, pin=where))
                if first_log is None:
                    first_log = (np.loadtxt(log), rows[-1])
            else:
                rows.append(run_python(controller, rate, Path(tmp) / f"{controller}-{rate:g}"))
            if echo:
                print(" ".join(f"{k} {v}" for k, v in rows[-1].items()), flush=True)
    return rows, first_log


def highest_rate(rows: list[dict], controller: str) -> float | None:
    """The highest rate at which ``controller`` missed fewer than 0.1% of its deadlines."""
    kept = [float(r["rate_hz"]) for r in rows
            if r["controller"] == controller and r["keeps_up"] == "yes"
            and r["scheduler"] == "other"]
    return max(kept) if kept else None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--controllers", nargs="+",
                   choices=["node", "node-signed", "node-student", *PYTHON_RUNS],
                   default=["node", *PYTHON_RUNS], help="which controllers (default all)")
    p.add_argument("--steps", type=int, default=5000,
                   help="the node's steps per rate (default 5000)")
    p.add_argument("--rates", type=float, nargs="+", default=[100, 200, 500, 1000, 2000],
                   help="plant rates to try with the node, Hz")
    p.add_argument("--python-rates", type=float, nargs="+", default=[20, 50, 100, 200],
                   help="plant rates to try with the Python controllers, Hz")
    p.add_argument("--repeats", type=int, default=1,
                   help="rounds of the node controllers per rate, each round in the reverse "
                        "order of the one before (ABBA for node and node-signed; default 1)")
    p.add_argument("--fifo", type=int, default=0, metavar="PRIORITY",
                   help="also run each node run with the plant and the node under SCHED_FIFO "
                        "at this priority (chrt; needs CAP_SYS_NICE), beside the default "
                        "scheduler's run (default 0: not)")
    p.add_argument("--pin", action="store_true",
                   help="also run each node run with the plant and the node held on CPUs of "
                        "their own (taskset: the first two this process may use), beside the "
                        "unpinned run")
    p.add_argument("--student", type=Path, default=None,
                   help="node-student: the student checkpoint (default: the cached one of "
                        "`python -m ftc.experiments.adaptive train`)")
    p.add_argument("--results", type=Path, help="write the table as a result file")
    p.add_argument("--signing-results", type=Path,
                   help="write the signing's cost per rate (node against node-signed) as a "
                        "result file")
    p.add_argument("--figure", type=Path, help="draw the latency histogram at the lowest rate")
    args = p.parse_args(argv)
    if args.repeats < 1:
        p.error(f"--repeats must be at least 1, not {args.repeats}")
    if not 0 <= args.fifo <= 99:
        p.error(f"--fifo must be a SCHED_FIFO priority in 1..99 (0: not), not {args.fifo}")
    cpus = pin_cpus() if args.pin else None
    load_start = os.getloadavg()[0]
    rows, first_log = measure(args.controllers, args.steps, args.rates, args.python_rates,
                              echo=True, repeats=args.repeats, student=args.student,
                              fifo=args.fifo, pin=cpus)
    for controller in dict.fromkeys(args.controllers):
        best = highest_rate(rows, controller)
        print(f"bench_realtime: {controller}: highest rate with < 0.1% misses: "
              + (f"{best:g} Hz" if best else "none tried"))
    cost = signing_cost(rows)
    for c in cost:
        print(f"bench_realtime: signing at {c['rate_hz']} Hz ({c['pairs']} pairs): p99 "
              f"{c['p99_unsigned_us']} us unsigned, {c['p99_signed_us']} us signed (medians), "
              f"+{c['difference_us']} us against a budget of {c['budget_us']} us: "
              f"{'within' if c['within_budget'] == 'yes' else 'OVER'}; HMAC "
              f"{c['hmac_us_per_step']} us per step")
    if args.signing_results and cost:
        from suite_results import write_result_file

        write_result_file(args.signing_results, (
            f"# what: the policy node's p99 latency (state arrival, before its check, to "
            f"command sent) unsigned and signed (HMAC-SHA256 on every message, plant and node "
            f"--key-file), {args.steps} steps a run, {args.repeats} pairs per rate alternating "
            f"ABBA, single fault; budget max(5% of the unsigned p99, 20 us); hmac: the node's "
            f"own time signing and checking, per step\n"
            f"# command: scripts/bench_realtime.py --controllers node node-signed --steps "
            f"{args.steps} --rates {' '.join(f'{r:g}' for r in args.rates)} --repeats "
            f"{args.repeats}\n"
            f"# commit: {git_revision()}\n"), cost)
    if args.results:
        from suite_results import write_result_file

        shape = ""
        if "node-student" in args.controllers:
            with tempfile.TemporaryDirectory() as tmp:  # the flown student's shape
                student_weights(args.student, Path(tmp) / "student.txt")
                shape = student_shape(Path(tmp) / "student.txt")
        write_result_file(args.results, (
            f"# what: controllers on the plant in real-time mode, single fault: node = "
            f"build/policy_node, {args.steps} steps per rate, a fresh 6-64-64-16-16-6 policy; "
            + (f"node-student = build/policy_node flying the adaptive student "
               f"({shape}) of {student_name(args.student)}; "
               if "node-student" in args.controllers else "") +
            f"ppo = ftc.controller ppo-offline learning on, mpc = ftc.mpc oracle-mpc, robust = "
            f"ftc.controller ppo-robust (guided fits), 2 x 256 steps and the evaluations; "
            f"latency: state received to command sent\n"
            f"# command: scripts/bench_realtime.py --controllers {' '.join(args.controllers)} "
            f"--steps {args.steps} --rates {' '.join(f'{r:g}' for r in args.rates)} "
            f"--python-rates {' '.join(f'{r:g}' for r in args.python_rates)}"
            + (f" --fifo {args.fifo}" if args.fifo else "")
            + (" --pin" if args.pin else "")
            + (f" --repeats {args.repeats}" if args.repeats > 1 else "")
            + (f" --student {args.student}" if args.student else "") + "\n"
            f"# commit: {git_revision()}\n"
            f"# date: {time.strftime('%Y-%m-%d', time.gmtime())}, load average "
            f"{load_start:.1f} at the start, {os.getloadavg()[0]:.1f} at the end\n"), rows)
    if args.figure and first_log is not None:
        first_log, first = first_log
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 3.2))
        ax.hist(first_log, bins=60, color="#4477aa")  # the node's latencies, microseconds
        ax.set_yscale("log")
        ax.set_xlabel("latency, state received to command sent (microseconds)")
        ax.set_ylabel("steps")
        ax.set_title(f"policy_node at {first['rate_hz']} Hz, {first['steps']} steps: "
                     f"p50 {first['latency_p50_us']} us, p99 {first['latency_p99_us']} us",
                     fontsize=9)
        fig.tight_layout()
        args.figure.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(args.figure, dpi=100)
        print(f"bench_realtime: figure -> {args.figure}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
