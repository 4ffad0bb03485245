"""scripts/bench_realtime.py: the order of its node runs, and a short real run
with the plant and the node pinned to CPUs of their own (the latencies are
timing, measured by the script, not asserted here)."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "scripts"))

import bench_realtime  # noqa: E402


def test_repeated_rounds_reverse_their_order_so_a_load_change_falls_on_every_controller():
    order = bench_realtime._node_runs(["node", "node-student", "ppo"], [200, 100], repeats=3)
    assert order == [("node", 100), ("node-student", 100), ("node-student", 100), ("node", 100),
                     ("node", 100), ("node-student", 100),
                     ("node", 200), ("node-student", 200), ("node-student", 200), ("node", 200),
                     ("node", 200), ("node-student", 200)]
    # the signing's pairs: ABBA
    assert [c for c, _ in bench_realtime._node_runs(["node", "node-signed"], [100], 2)] == [
        "node", "node-signed", "node-signed", "node"]


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="--pin needs two CPUs")
def test_a_pinned_run_flies_the_node_on_the_plant_beside_the_unpinned_one(tmp_path):
    out = tmp_path / "rt.csv"
    done = subprocess.run([sys.executable, str(REPO / "scripts" / "bench_realtime.py"),
                           "--controllers", "node", "--steps", "40", "--rates", "100",
                           "--pin", "--results", str(out)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    lines = out.read_text().splitlines()
    assert lines[1].endswith("--pin")
    rows = list(csv.DictReader(line for line in lines if not line.startswith("#")))
    first, second = sorted(os.sched_getaffinity(0))[:2]
    assert [r["scheduler"] for r in rows] == ["other", f"other, pinned {first}/{second}"]
    assert all(r["controller"] == "node" and r["steps"] == "40" for r in rows)


def test_pin_refuses_a_process_held_to_one_cpu():
    cpu = min(os.sched_getaffinity(0))
    done = subprocess.run(["taskset", "-c", str(cpu), sys.executable,
                           str(REPO / "scripts" / "bench_realtime.py"), "--controllers", "node",
                           "--steps", "10", "--rates", "100", "--pin"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode != 0
    assert "--pin needs two CPUs" in done.stderr
