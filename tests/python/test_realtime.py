"""The Python controller on a plant in real-time mode (the plant does not
wait): a learning run reports its deadlines; stopped for 2 s (SIGSTOP) the
controller lets the plant's watchdog close the valves, then takes control
back and reports the trip; killed, it leaves the plant in the safe state; a
plant that restarts under it ends the run with one line.

Every test drives the real plant binary over LCM on a private port and
prefix. Rates are 20 Hz (50 ms a step): what is asserted holds whatever the
machine's load, except where a comment says what load would break it."""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import lcm
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from ftc.common.build_info import plant_binary
from ftc.control.run.config import RUN_FILES
from ftc.control.run.realtime import REALTIME_COLUMNS
from ftc.plant import private_lcm_url, private_prefix
from ftc.plant_state_t import plant_state_t

REPO = Path(__file__).resolve().parents[2]
ENV = {**os.environ, "PYTHONPATH": str(REPO / "python"), "OMP_NUM_THREADS": "1"}
RATE = 20
SHORT = ["--no-pretrain"]


class Listener:
    """Every state a plant publishes, in a background thread (as a recorder would)."""

    def __init__(self, url: str, prefix: str) -> None:
        self.states: list[plant_state_t] = []
        self._lc = lcm.LCM(url)
        self._lc.subscribe(prefix + "STATE",
                           lambda _c, data: self.states.append(plant_state_t.decode(data)))
        self._stop = False
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop:
            self._lc.handle_timeout(50)

    def since(self, t_ns: int) -> list[plant_state_t]:
        return [s for s in list(self.states) if s.utime * 1000 >= t_ns]

    def close(self) -> None:
        self._stop = True
        self._thread.join()


def _plant(url: str, prefix: str, scenarios: Path, watchdog: float = 0.5) -> subprocess.Popen:
    return subprocess.Popen(
        [str(plant_binary()), "--lcm-url", url, "--prefix", prefix, "--scenario",
         str(scenarios / "single.toml"), "--steps-per-interval", "128", "--mode", "realtime",
         "--rate", str(RATE), "--watchdog", str(watchdog)],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _controller(url: str, prefix: str, out: Path, intervals: int = 2) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "ftc.controller", *SHORT, "--attach", "--lcm-url", url,
         "--prefix", prefix, "--intervals", str(intervals), "--steps-per-interval", "128",
         "--update-every", "64", "--no-offline", "--out", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV, cwd=REPO)


def _rows(path: Path) -> list[dict[str, str]]:
    try:
        with open(path / "metrics.csv") as f:
            return list(csv.DictReader(f))
    except OSError:
        return []


def _wait_for(listener: Listener, what, predicate, timeout: float = 60.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate(list(listener.states)):
            return
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def _controlled(states) -> bool:
    """The last few steps were taken on the controller's commands."""
    steps = [s for s in states[-5:] if s.step > 0]
    return len(steps) >= 3 and not any(s.watchdog_tripped for s in steps)


@pytest.fixture
def bus(scenarios):
    url, prefix = private_lcm_url(), private_prefix()
    plant = _plant(url, prefix, scenarios)
    listener = Listener(url, prefix)
    yield url, prefix, plant, listener
    listener.close()
    if plant.poll() is None:
        plant.kill()
    plant.wait()


def _deadline_counts_are_steps(row: dict, steps_per_interval: int) -> None:
    """The two miss counts of an interval are counts of its steps. Neither bounds
    the other: the plant also counts the ticks between the run's phases, and a
    late answer to an older state, applied because nothing newer came, is fresh
    to the plant but a miss to the controller (seen on a loaded machine: 2
    misses, 1 missed tick). How many there are is timing: bench_realtime.py."""
    steps = steps_per_interval + int(row["eval_steps"] or 0)
    assert 0 <= int(row["deadline_misses"]) <= steps, row
    assert int(row["plant_missed_ticks"]) >= 0, row


def test_a_learning_run_on_a_realtime_plant_reports_its_deadlines(tmp_path):
    out = tmp_path / "rt"
    # launched by the controller itself; PPO updates every 32 steps and the
    # offline phase run off the control loop
    proc = subprocess.run(
        [sys.executable, "-m", "ftc.controller", "--no-pretrain", "--model-episodes", "4",
         "--offline-steps", "256", "--realtime", str(RATE), "--intervals", "2",
         "--steps-per-interval", "64", "--update-every", "32", "--tensorboard",
         str(tmp_path / "tb"), "--out", str(out)],
        capture_output=True, text=True, env=ENV, cwd=REPO, timeout=300)
    assert proc.returncode == 0, proc.stderr
    rows = _rows(out)
    assert [r["interval"] for r in rows] == ["0", "1"]
    for r in rows:
        p50, p99, worst = (float(r[c]) for c in ("latency_p50_ms", "latency_p99_ms",
                                                  "latency_max_ms"))
        assert 0 < p50 <= p99 <= worst
        _deadline_counts_are_steps(r, 64)
        assert int(r["eval_steps"]) > 0
    # the offline phase of interval 0 ran in the background and was reported late
    assert rows[0]["offline_reward_per_step"] != ""
    events = EventAccumulator(str(tmp_path / "tb"))
    events.Reload()
    for column in REALTIME_COLUMNS:
        logged = [e.value for e in events.Scalars(f"interval/{column}")]
        assert logged == pytest.approx([float(r[column]) for r in rows], rel=1e-5), column


@pytest.mark.slow  # 10-30 s: the fresh-clone CI stays under its 10 minutes
def test_a_stopped_controller_trips_the_watchdog_and_then_takes_control_back(bus, tmp_path):
    url, prefix, plant, listener = bus
    out = tmp_path / "run"
    proc = _controller(url, prefix, out, intervals=3)
    try:
        _wait_for(listener, "the controller to take control", _controlled)
        proc.send_signal(signal.SIGSTOP)
        stopped = time.time_ns()
        time.sleep(2.0)  # four times the plant's 0.5 s watchdog
        proc.send_signal(signal.SIGCONT)
        resumed = time.time_ns()
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    during = [s for s in listener.since(stopped) if s.utime * 1000 < resumed]
    tripped = [s for s in during if s.watchdog_tripped]
    # 2 s at 20 Hz, the first 0.5 s on the last command: about 30 ticks in the safe state
    assert len(tripped) >= 20
    assert all(list(s.valve) == [0] * 6 for s in tripped if s.step > 0)
    after = [s for s in listener.since(resumed) if s.step > 0]
    assert _controlled(after[10:40])  # control taken back
    rows = _rows(out)
    assert len(rows) == 3
    assert sum(int(r["watchdog_trips"]) for r in rows) >= 1
    assert sum(int(r["deadline_misses"]) for r in rows) >= 30  # every tick of the stop


def test_a_killed_controller_leaves_the_plant_in_the_safe_state(bus, tmp_path):
    url, prefix, plant, listener = bus
    proc = _controller(url, prefix, tmp_path / "run", intervals=5)
    try:
        _wait_for(listener, "the controller to take control", _controlled)
        proc.kill()
        killed = time.time_ns()
        proc.wait()
        time.sleep(1.5)  # the 0.5 s watchdog, and 1 s of ticks after it
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert plant.poll() is None  # the plant runs on
    late = [s for s in listener.since(killed + 700_000_000) if s.step > 0]
    assert len(late) >= 10
    assert all(s.watchdog_tripped and list(s.valve) == [0] * 6 for s in late)


def test_a_plant_that_restarts_under_the_controller_ends_the_run_with_one_line(
        bus, tmp_path, scenarios):
    url, prefix, plant, listener = bus
    out = tmp_path / "run"
    proc = _controller(url, prefix, out, intervals=5)
    try:
        _wait_for(listener, "the controller to take control", _controlled)
        plant.kill()
        plant.wait()
        again = _plant(url, prefix, scenarios)
        try:
            _, err = proc.communicate(timeout=60)
        finally:
            again.kill()
            again.wait()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 3, err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "restarted" in lines[0] or "published no state" in lines[0], lines[0]
    # it stopped within interval 0 (6.4 s at 20 Hz): no partial run is left behind
    assert not any((out / name).exists() for name in RUN_FILES), list(out.iterdir())


@pytest.mark.slow  # 10-30 s: the fresh-clone CI stays under its 10 minutes
def test_a_guided_methods_fits_run_off_the_loop_and_report_late(tmp_path):
    out = tmp_path / "robust"
    # ppo-robust: after each interval the guided fit (DAgger with the planner, about
    # a second) runs on a worker thread while a frozen copy of the policy acts
    proc = subprocess.run(
        [sys.executable, "-m", "ftc.controller", "--method", "ppo-robust", "--offline-steps",
         "0", "--realtime", str(RATE), "--intervals", "2", "--steps-per-interval", "128",
         "--update-every", "64", "--quiet", "--out", str(out)],
        capture_output=True, text=True, env=ENV, cwd=REPO, timeout=300)
    assert proc.returncode == 0, proc.stderr
    rows = _rows(out)
    assert [r["interval"] for r in rows] == ["0", "1"]
    for r in rows:  # each interval's fit reported, after the interval had moved on
        assert float(r["teach_seconds"]) > 0 and int(r["teacher_labels"]) > 0
        _deadline_counts_are_steps(r, 128)
