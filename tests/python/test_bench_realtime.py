"""scripts/bench_realtime.py: the order of its node runs, and a short real run
with the plant and the node pinned to CPUs of their own (the latencies are
timing, measured by the script, not asserted here)."""

from __future__ import annotations

import csv
import os
import subprocess
import sys
import time
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


def _children(pid: int) -> dict[int, str]:
    """pid -> executable name of the processes whose parent is ``pid``."""
    out = {}
    for d in Path("/proc").iterdir():
        try:
            status = (d / "status").read_text()
        except (FileNotFoundError, NotADirectoryError, ProcessLookupError, PermissionError):
            continue
        fields = dict(line.split(":\t", 1) for line in status.splitlines() if ":\t" in line)
        if fields.get("PPid", "").strip() == str(pid):
            out[int(d.name)] = fields["Name"].strip()
    return out


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="--pin needs two CPUs")
def test_a_pinned_run_holds_the_plant_and_the_node_on_their_cpus(tmp_path):
    # the bench's children, watched while they run: in the pinned run the plant is
    # held on the first CPU and the node on the second (3 s each run at 100 Hz)
    out = tmp_path / "rt.csv"
    bench = subprocess.Popen([sys.executable, str(REPO / "scripts" / "bench_realtime.py"),
                              "--controllers", "node", "--steps", "300", "--rates", "100",
                              "--pin", "--results", str(out)],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    first, second = sorted(os.sched_getaffinity(0))[:2]
    seen: dict[str, set] = {"plant": set(), "policy_node": set()}
    while bench.poll() is None:
        for pid, name in _children(bench.pid).items():
            if name in seen:
                try:
                    seen[name].add(frozenset(os.sched_getaffinity(pid)))
                except ProcessLookupError:
                    pass
        time.sleep(0.05)
    assert bench.returncode == 0, bench.stderr.read()
    assert frozenset({first}) in seen["plant"] and frozenset({second}) in seen["policy_node"]
    assert frozenset({second}) not in seen["plant"]
    assert frozenset({first}) not in seen["policy_node"]
    lines = out.read_text().splitlines()
    assert lines[1].endswith("--pin")
    rows = list(csv.DictReader(line for line in lines if not line.startswith("#")))
    assert [r["scheduler"] for r in rows] == ["other", f"other, pinned {first}/{second}"]
    assert all(r["controller"] == "node" and r["steps"] == "300" for r in rows)


def test_pin_refuses_a_process_held_to_one_cpu():
    cpu = min(os.sched_getaffinity(0))
    done = subprocess.run(["taskset", "-c", str(cpu), sys.executable,
                           str(REPO / "scripts" / "bench_realtime.py"), "--controllers", "node",
                           "--steps", "10", "--rates", "100", "--pin"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode != 0
    assert "--pin needs two CPUs" in done.stderr
