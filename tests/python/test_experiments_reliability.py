"""The experiments orchestrator and ftc.simulate under faults (Reliability
items 3, 6 and 8):

  * a full disk (a small tmpfs; needs root, as CI runs, skipped with the reason
    otherwise): one line naming the path, exit 5, no temporary file; --resume
    completes once space is back, with the results of a run that never failed;
  * --out that is a directory for ftc.simulate: exit 2 before the plant starts;
  * SIGKILL of the orchestrator: no orphan process (every descendant seen
    while it ran is gone), a second orchestrator on the same --out is refused
    while the first runs, and --resume takes the stale lock over and completes
    with the results of an uninterrupted run;
  * the soak (slow): 20 rounds of SIGKILL of a reduced ``all`` on a fixed
    schedule of progress events (mid-run, or right after a run finished), each
    followed by --resume; every round is killed while runs remain.

Results are compared on every column of results.csv but the timing ones, and
the baseline episodes byte for byte. Set FTC_FAULT_TALLY=<file> for the counts.
"""

from __future__ import annotations

import csv
import hashlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import NamedTuple

import pytest

REPO = Path(__file__).resolve().parents[2]
PY = sys.executable
TIMING = {"online_seconds", "offline_seconds", "wall_time"}
# closed and open, and a slower method (PPO learns online)
REDUCED = ["single", "--methods", "closed", "open", "ppo-online", "--intervals", "2",
           "--steps-per-interval", "128", "--jobs", "2"]
SOAK = ["all", "--methods", "closed", "open", "--trials", "1", "--intervals", "2",
        "--steps-per-interval", "128", "--jobs", "2"]


def tally(what: str, n: int) -> None:
    path = os.environ.get("FTC_FAULT_TALLY")
    if path:
        with open(path, "a") as f:
            f.write(json.dumps({"what": what, "n": n}) + "\n")


def _experiments(args: list[str], timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([PY, "-m", "ftc.experiments", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=REPO)


def _results(out: Path) -> list[dict]:
    with open(out / "results.csv", newline="") as f:
        rows = [{k: v for k, v in r.items() if k not in TIMING} for r in csv.DictReader(f)]
    return sorted(rows, key=lambda r: (r["experiment"], r["trial"], r["method"], r["seed"],
                                       int(r["interval"])))


def _baselines(out: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted((out / "baselines").glob("*.csv"))}


def _assert_same_results(out: Path, reference: Path) -> int:
    """Asserts equal results; returns the number of result rows compared."""
    got, want = _results(out), _results(reference)
    assert got == want, f"{len(got)} rows vs {len(want)}"
    assert _baselines(out) == _baselines(reference)
    assert not list(out.rglob("*.tmp")), list(out.rglob("*.tmp"))
    assert not (out / "orchestrator.lock").exists()
    return len(got)


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("reference") / "run"
    proc = _experiments([*REDUCED, "--out", str(out)])
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out


# ---------------------------------------------------------------------------
# Processes: descendants and orphans
# ---------------------------------------------------------------------------

def _start_time(pid: int) -> str | None:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


def _descendants(pid: int) -> set[tuple[int, str]]:
    found, todo = set(), [pid]
    while todo:
        p = todo.pop()
        try:
            tasks = os.listdir(f"/proc/{p}/task")
        except OSError:
            continue
        for t in tasks:
            try:
                children = Path(f"/proc/{p}/task/{t}/children").read_text().split()
            except OSError:
                continue
            for c in map(int, children):
                start = _start_time(c)
                if start:
                    found.add((c, start))
                    todo.append(c)
    return found


class Watcher:
    """Records every descendant of a process while it runs (polled every 20 ms)."""

    def __init__(self, pid: int) -> None:
        self.pid, self.seen = pid, set()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            self.seen |= _descendants(self.pid)
            self._stop.wait(0.02)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


def _orphans(seen: set[tuple[int, str]], out: Path, deadline_s: float = 15.0) -> list[str]:
    """Descendants still alive ``deadline_s`` after their orchestrator died, and
    any process naming ``out`` on its command line."""
    deadline = time.monotonic() + deadline_s
    while True:
        alive = [pid for pid, start in seen if _start_time(pid) == start]
        named = []
        for entry in os.listdir("/proc"):
            if entry.isdigit():
                try:
                    cmd = Path(f"/proc/{entry}/cmdline").read_bytes().replace(b"\0", b" ")
                except OSError:
                    continue
                if str(out).encode() in cmd:
                    named.append(int(entry))
        left = sorted(set(alive) | set(named))
        if not left or time.monotonic() > deadline:
            return [Path(f"/proc/{p}/cmdline").read_bytes().replace(b"\0", b" ").decode(
                errors="replace")[:200] for p in left if Path(f"/proc/{p}").exists()]
        time.sleep(0.05)  # polling for an observable state: the processes being gone


def _wait_for(pred, proc: subprocess.Popen, timeout: float = 300) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        assert proc.poll() is None, "the orchestrator ended before the moment to kill it"
        assert time.monotonic() < deadline, "timed out waiting for the orchestrator"
        time.sleep(0.02)


def _processes(run_dir: Path) -> dict:
    try:
        return json.loads((run_dir / "processes.json").read_text())
    except (OSError, ValueError):
        return {}


# ---------------------------------------------------------------------------
# SIGKILL, the lock, --resume
# ---------------------------------------------------------------------------

def test_sigkill_leaves_no_orphans_the_lock_refuses_and_resume_completes(tmp_path, reference):
    out = tmp_path / "run"
    proc = subprocess.Popen([PY, "-m", "ftc.experiments", *REDUCED, "--out", str(out)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=REPO)
    watcher = Watcher(proc.pid)
    slow = out / "runs" / "single" / "t00" / "ppo-online" / "s0"
    try:
        # the slow method's controller and its plant running
        _wait_for(lambda: "controller" in _processes(slow)
                  and len(_descendants(_processes(slow)["controller"]["pid"])) >= 1, proc)
        assert proc.poll() is None
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    finally:
        watcher.stop()
        if proc.poll() is None:
            proc.kill()
    assert len(watcher.seen) >= 4  # guardian, controllers, their plants, recorders
    orphans = _orphans(watcher.seen, out)
    assert orphans == [], orphans
    assert json.loads((out / "orchestrator.lock").read_text())["pid"] == proc.pid  # stale
    # --resume takes the stale lock over; a second orchestrator meanwhile is refused
    resumed = subprocess.Popen([PY, "-m", "ftc.experiments", *REDUCED, "--out", str(out),
                                "--resume"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                               text=True, cwd=REPO)
    try:
        _wait_for(lambda: json.loads((out / "orchestrator.lock").read_text() or "{}")
                  .get("pid") == resumed.pid, resumed)
        second = _experiments([*REDUCED, "--out", str(out), "--resume"], timeout=120)
        assert second.returncode == 2, second.stderr
        lines = second.stderr.strip().splitlines()
        assert len(lines) == 1 and f"pid {resumed.pid}" in lines[0] and "in use" in lines[0], \
            lines
        _, err = resumed.communicate(timeout=600)
    finally:
        if resumed.poll() is None:
            resumed.kill()
    assert resumed.returncode == 0, err[-3000:]
    assert "taking over the stale lock" in err and f"pid {proc.pid} on " in err
    _assert_same_results(out, reference)
    tally("orchestrator SIGKILLed mid-run", 1)


# ---------------------------------------------------------------------------
# Full disk
# ---------------------------------------------------------------------------

@pytest.fixture
def small_disk(tmp_path):
    mount = tmp_path / "disk"
    mount.mkdir()
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mount)],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({proc.stderr.strip() or proc.returncode}); "
                    "the storage-fault tests need root")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def _grow(mount: Path, size: str = "64m") -> None:
    subprocess.run(["mount", "-o", f"remount,size={size}", str(mount)], check=True)


def test_simulate_on_a_full_disk_exits_5_naming_the_file_and_leaves_nothing(small_disk):
    out = small_disk / "traj.csv"
    proc = subprocess.run([PY, "-m", "ftc.simulate", "--policy", "random", "--steps", "3000",
                           "--out", str(out)], capture_output=True, text=True, timeout=120,
                          cwd=REPO)
    assert proc.returncode == 5, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ftc.simulate: error: cannot write ") \
        and str(out) in lines[0] and "No space left" in lines[0], lines
    assert list(small_disk.iterdir()) == []
    tally("full disk under ftc.simulate", 1)


def test_simulate_out_that_is_a_directory_exits_2_before_the_plant_starts(tmp_path):
    start = time.monotonic()
    proc = subprocess.run([PY, "-m", "ftc.simulate", "--steps", "100000000", "--out",
                           str(tmp_path)], capture_output=True, text=True, timeout=60, cwd=REPO)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "--out" in lines[0] and "is a directory" in lines[0], lines
    assert time.monotonic() - start < 30
    assert list(tmp_path.iterdir()) == []


def test_the_lock_removes_temporaries_when_taken_and_when_released(tmp_path):
    """A run stopped by SIGTERM mid-write (the disk filled under another run)
    leaves its atomic write's temporary file behind: the lock's holder removes
    such leftovers when it takes the lock and after every run has stopped."""
    from ftc.experiments.processes import OrchestratorLock

    out = tmp_path / "run"
    stale = out / "runs" / "single" / "t00" / "ppo-online" / "s0" / "controller"
    stale.mkdir(parents=True)
    (stale / "checkpoint.pt.abc.tmp").write_bytes(b"half")
    (stale / "checkpoint.pt").write_bytes(b"whole")
    lock = OrchestratorLock(out).acquire()
    assert not list(out.rglob("*.tmp"))
    (stale / "metrics.csv.def.tmp").write_text("cut short")
    lock.release()
    assert not list(out.rglob("*.tmp"))
    assert (stale / "checkpoint.pt").read_bytes() == b"whole"
    assert not (out / "orchestrator.lock").exists()


def test_experiment_on_a_full_disk_exits_5_and_resume_completes(small_disk, reference):
    out = small_disk / "run"
    proc = _experiments([*REDUCED, "--out", str(out)])
    assert proc.returncode == 5, proc.stderr[-3000:]
    lines = proc.stderr.strip().splitlines()
    errors = [line for line in lines if "error:" in line]
    assert len(errors) == 1 and errors[0] == lines[-1], lines[-10:]
    assert lines[-1].startswith("ftc.experiments: error: cannot write ") \
        and str(out) in lines[-1], lines[-1]
    assert not list(out.rglob("*.tmp")), list(out.rglob("*.tmp"))
    assert not (out / "orchestrator.lock").exists()
    _grow(small_disk)
    done = _experiments([*REDUCED, "--out", str(out), "--resume"])
    assert done.returncode == 0, done.stderr[-3000:]
    _assert_same_results(out, reference)
    tally("full disk under ftc.experiments", 1)


# ---------------------------------------------------------------------------
# Soak
# ---------------------------------------------------------------------------

class Kill(NamedTuple):
    """When a soak round SIGKILLs its orchestrator: ``delay`` s after the
    round's ``after_results``-th new result.json appears (right after a run
    finished), or, with ``after_results`` 0, ``delay`` s after the round's first
    controller is seen running (mid-run)."""

    after_results: int
    delay: float


# One entry per round. Why the number of kills is deterministic: every kill is
# triggered by the round's own progress, not by wall time, and the schedule
# cannot use up the work before its last kill. A SOAK run takes about 0.4 s
# (more on a loaded machine) from its controller's start to its result.json, so
# a mid-run round (delays <= 0.2 s) finishes no run; an after-result round
# finishes its `after_results` runs plus at most the one other run in flight
# (--jobs 2), since a result.json the schedule did not ask for triggers the kill
# at once (_wait_to_kill). The whole schedule thus finishes at most
# SOAK_RESULT_BUDGET (4) of SOAK's 6 runs: every round still has runs to do when
# its kill comes, so it cannot exit before it.
SOAK_KILLS = [
    Kill(0, 0.0), Kill(0, 0.1), Kill(0, 0.2), Kill(1, 0.0), Kill(0, 0.05),
    Kill(0, 0.15), Kill(0, 0.0), Kill(0, 0.1), Kill(0, 0.2), Kill(0, 0.05),
    Kill(1, 0.1), Kill(0, 0.15), Kill(0, 0.0), Kill(0, 0.1), Kill(0, 0.2),
    Kill(0, 0.05), Kill(0, 0.15), Kill(0, 0.0), Kill(0, 0.1), Kill(0, 0.2),
]
SOAK_JOBS = int(SOAK[SOAK.index("--jobs") + 1])
SOAK_RESULT_BUDGET = sum(k.after_results + SOAK_JOBS - 1 for k in SOAK_KILLS if k.after_results)


def _finished_runs(out: Path) -> set[Path]:
    return set(out.glob("runs/**/result.json"))


def _controller_running(out: Path) -> bool:
    """A run's controller is alive (earlier rounds' processes are all gone)."""
    for path in out.glob("runs/**/processes.json"):
        controller = _processes(path.parent).get("controller", {})
        if controller.get("pid") and _start_time(controller["pid"]) == controller.get("start"):
            return True
    return False


def _wait_to_kill(p: subprocess.Popen, out: Path, kill: Kill, before: set[Path],
                  timeout: float = 300) -> int:
    """Waits for the moment ``kill`` names, or for a result.json it did not ask
    for (then at once); returns the number of such unscheduled results."""
    deadline, since = time.monotonic() + timeout, None
    while True:
        new = len(_finished_runs(out) - before)
        if new > kill.after_results:
            return new - kill.after_results
        if since is None and (new == kill.after_results if kill.after_results
                              else _controller_running(out)):
            since = time.monotonic()
        if since is not None and time.monotonic() - since >= kill.delay:
            return 0
        assert p.poll() is None, \
            f"the orchestrator ended before its kill {kill}: {p.stderr.read().decode()[-2000:]}"
        assert time.monotonic() < deadline, f"timed out waiting for the moment of {kill}"
        time.sleep(0.01)


@pytest.mark.slow
def test_soak_sigkill_on_a_fixed_schedule_then_resume(tmp_path):
    reference = tmp_path / "reference"
    proc = _experiments([*SOAK, "--out", str(reference)], timeout=1200)
    assert proc.returncode == 0, proc.stderr[-3000:]
    runs = len(_finished_runs(reference))
    assert SOAK_RESULT_BUDGET < runs, (SOAK_RESULT_BUDGET, runs)
    out = tmp_path / "soak"
    counts = {"rounds": 0, "kills": 0, "killed_mid_run": 0, "killed_after_a_result": 0,
              "unscheduled_results": 0, "fewest_runs_left": runs, "orphans": 0,
              "runs_survived": 0, "results_lost": 0}
    finished: dict[str, str] = {}  # run directory -> digest of result.json when first seen
    for kill in SOAK_KILLS:
        counts["rounds"] += 1
        before = _finished_runs(out)
        p = subprocess.Popen([PY, "-m", "ftc.experiments", *SOAK, "--out", str(out), "--resume"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=REPO)
        watcher = Watcher(p.pid)
        try:
            counts["unscheduled_results"] += _wait_to_kill(p, out, kill, before)
            p.send_signal(signal.SIGKILL)
            p.wait()
        finally:
            watcher.stop()
            if p.poll() is None:
                p.kill()
                p.wait()
            p.stderr.close()
        # only the orchestrator writes result.json: none appears once it is dead
        runs_left = runs - len(_finished_runs(out))
        assert runs_left > 0, f"round {counts['rounds']}: every run finished before its kill"
        counts["fewest_runs_left"] = min(counts["fewest_runs_left"], runs_left)
        if p.returncode == -signal.SIGKILL:
            counts["kills"] += 1
            counts["killed_after_a_result" if kill.after_results else "killed_mid_run"] += 1
        orphans = _orphans(watcher.seen, out)
        counts["orphans"] += len(orphans)
        assert orphans == [], orphans
        for result in out.glob("runs/**/result.json"):
            digest = hashlib.sha256(result.read_bytes()).hexdigest()
            if str(result) in finished:
                assert finished[str(result)] == digest, f"{result} changed after it finished"
            else:
                finished[str(result)] = digest
    done = _experiments([*SOAK, "--out", str(out), "--resume"], timeout=1200)
    assert done.returncode == 0, done.stderr[-3000:]
    for path, digest in finished.items():
        kept = Path(path).is_file() and hashlib.sha256(Path(path).read_bytes()).hexdigest() == digest
        counts["runs_survived" if kept else "results_lost"] += 1
    want, got = _results(reference), _results(out)
    counts["results_lost"] += sum(1 for r in want if r not in got)
    counts["result_rows"] = _assert_same_results(out, reference)
    print("soak:", json.dumps(counts))
    tally("soak SIGKILLs of ftc.experiments", counts["kills"])
    assert counts["kills"] == len(SOAK_KILLS), counts  # every round was cut short
