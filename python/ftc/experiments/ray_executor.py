"""Runs as Ray tasks (``--executor ray [--ray-address ADDR]``): each run, and
each baseline episode, is one task on some node of a Ray cluster, with its own
plant, recorder and private LCM URL and prefix on that node, exactly as the
local executor runs it (runs.execute_with_retries).

Shared nothing: a task runs in a temporary directory of its node and returns
the run directory's files as bytes; the driver writes them into OUT, each
atomically and result.json last, so the driver's OUT is the only copy, a run
counts as finished under the same rule as a local one, and --resume (with
either executor) skips it. Every node must have the repository at the same
revision, built, with ``ftc`` importable by its Ray workers; the driver checks
each node's code identity (git revision and a hash of the Python sources)
before anything is written and refuses a node that differs.

Ray is imported inside functions: local runs do not pay for it.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import io
import logging
import os
import secrets
import shutil
import signal
import socket
import sys
import tempfile
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from ftc.common.atomic import atomic_write_bytes, atomic_write_json
from ftc.common.build_info import git_revision
from ftc.common.cli import checked
from ftc.common.errors import StorageError, UsageError
from ftc.experiments.processes import Guardian, RunFailed, RunHandle, stop_leftover_processes
from ftc.experiments.progress import Progress, count_rows
from ftc.experiments.runs import RunSpec, execute_with_retries, run_baseline_episode
from ftc.experiments.scenarios import ExperimentConfig

PACKAGE_DIR = Path(__file__).resolve().parents[1]
# Ray binds to the node's external address unless told the cluster is local;
# a loopback address (and the private local instance) keeps every socket on lo.
LOCAL_ONLY_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"
RESULT = "result.json"


class RayUnavailable(UsageError):
    """No usable Ray cluster: not installed, unreachable, or a node runs other code."""


def add_executor_options(parser: argparse.ArgumentParser) -> None:
    """--executor, --ray-address and --fork-server (the experiments' and the benchmark's)."""
    parser.add_argument("--executor", choices=("local", "ray"), default="local",
                        help="local: runs on this machine's pool of --jobs (default); ray: "
                             "each run a Ray task, on the cluster at --ray-address or a "
                             "private local Ray instance (docs/ecosystem.md)")
    parser.add_argument("--ray-address", type=checked(str, nonempty=True), default=None,
                        metavar="ADDR",
                        help="with --executor ray: the cluster's head (HOST:PORT as printed "
                             "by 'ray start --head', 'auto', or ray://HOST:PORT)")
    parser.add_argument("--fork-server", action=argparse.BooleanOptionalAction, default=True,
                        help="local runs: fork each run's controller from one process that "
                             "has imported torch and the controllers (default), instead of "
                             "starting a fresh python per run (--no-fork-server), which "
                             "spends 1-2 s of CPU per run on imports; results are the same "
                             "(ftc/experiments/fork_server.py)")


def check_executor_options(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse --ray-address without --executor ray (exit 2, one line) and resolve
    --jobs: locally the number of cores by default; on Ray no cap by default."""
    if args.ray_address is not None and args.executor != "ray":
        parser.error(f"--ray-address {args.ray_address}: only with --executor ray")
    if args.jobs is None and args.executor == "local":
        args.jobs = os.cpu_count() or 1


def code_identity(package_dir: Path = PACKAGE_DIR) -> dict[str, str]:
    """What a node would run: the repository's git revision and a hash of every
    Python source of the package (a dirty tree's revision alone says little)."""
    h = hashlib.sha256()
    for path in sorted(package_dir.rglob("*.py")):
        h.update(str(path.relative_to(package_dir)).encode() + b"\0" + path.read_bytes())
    return {"git_revision": git_revision(), "sources": h.hexdigest()[:16],
            "python": sys.version.split()[0]}


def node_identity() -> dict[str, Any]:
    """A task's report of its node (the driver's probe)."""
    return {"host": socket.gethostname(), **code_identity()}


def identity_problem(driver: dict, node: dict) -> str | None:
    """Why ``node`` (a :func:`node_identity`) cannot run the driver's runs, or None."""
    for key in ("git_revision", "sources", "python"):
        if node.get(key) != driver.get(key):
            return (f"node {node.get('host', '?')} runs {key.replace('_', ' ')} "
                    f"{node.get(key)}, the driver {driver.get(key)}; every node needs the "
                    "repository at the driver's revision, built")
    return None


def _loopback(address: str) -> bool:
    host = address.rpartition(":")[0] if ":" in address else address
    return host in ("localhost", "::1", "[::1]") or host.startswith("127.")


def _reachable(address: str, timeout: float = 5.0) -> None:
    """Refuse at once a HOST:PORT nobody listens on (Ray itself retries for minutes)."""
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit():
        raise RayUnavailable(f"--ray-address {address}: expected HOST:PORT, 'auto' or ray://...")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout).close()
    except OSError as e:
        raise RayUnavailable(f"--ray-address {address}: cannot reach a Ray head there "
                             f"({e.strerror or e})") from None


@dataclass
class RaySession:
    """A connection to a Ray cluster (or a private local instance).

    address: what was given (None: a local instance started by this process)
    jobs: at most this many runs in flight (None: as many as the cluster's CPUs)
    nodes: every alive node's :func:`node_identity`
    """

    address: str | None
    jobs: int | None
    identity: dict
    nodes: list[dict] = field(default_factory=list)
    cpus: float = 0.0
    temp_dir: str | None = None

    def describe(self) -> dict:
        """The executor's record for experiment.json / benchmark.json."""
        return {"kind": "ray", "address": self.address or "local", "cpus": self.cpus,
                "nodes": sorted(n["host"] for n in self.nodes)}

    def close(self) -> None:
        import ray

        ray.shutdown()
        if self.temp_dir:
            shutil.rmtree(self.temp_dir, ignore_errors=True)


def connect(address: str | None, jobs: int | None,
            object_store_bytes: int = 200 * 1024 * 1024) -> RaySession:
    """Connect to the Ray cluster at ``address`` (HOST:PORT, 'auto', ray://...)
    or, for None, start a private local instance (``jobs`` CPUs, no dashboard,
    loopback only); then check every node's code. Raises RayUnavailable with one
    line naming the address; nothing is written before this returns."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    if address is None or _loopback(address):
        os.environ[LOCAL_ONLY_ENV] = "0"
    if address is None and "RAY_AUTH_MODE" not in os.environ:
        # A token of this instance only, in the environment its processes inherit
        # (not in ~/.ray, where Ray would put one); read when ray is first imported.
        os.environ["RAY_AUTH_MODE"] = "token"
        os.environ["RAY_AUTH_TOKEN"] = secrets.token_hex(32)
    try:
        import ray
    except ImportError:
        raise RayUnavailable("--executor ray: the ray package is not installed "
                             "(requirements-extra.txt pins it)") from None
    if address is not None and address != "auto" and not address.startswith("ray://"):
        _reachable(address)
    session = RaySession(address, jobs, code_identity())
    where = f"--ray-address {address}" if address else "--executor ray"
    try:
        if address is None:
            session.temp_dir = tempfile.mkdtemp(prefix="ftc-ray-")
            ray.init(address="local", num_cpus=jobs or os.cpu_count() or 1,
                     include_dashboard=False, object_store_memory=object_store_bytes,
                     _temp_dir=session.temp_dir, logging_level=logging.WARNING,
                     log_to_driver=False)
        else:
            ray.init(address=address, logging_level=logging.WARNING, log_to_driver=False)
    except Exception as e:  # noqa: BLE001 - Ray raises several kinds; all mean "no cluster"
        if session.temp_dir:
            shutil.rmtree(session.temp_dir, ignore_errors=True)
        raise RayUnavailable(f"{where}: cannot connect to Ray ({_first_line(e)})") from None
    try:
        _check_nodes(ray, session, where)
    except BaseException:
        session.close()
        raise
    return session


def _first_line(e: BaseException) -> str:
    text = str(getattr(e, "cause", None) or e).strip()
    return f"{type(e).__name__}: {text.splitlines()[0] if text else ''}".rstrip(": ")


def _check_nodes(ray: Any, session: RaySession, where: str, timeout: float = 120.0) -> None:
    """One probe task pinned to each alive node: its code must be the driver's."""
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    alive = [n for n in ray.nodes() if n.get("Alive")]
    probe = ray.remote(num_cpus=0, max_retries=0)(node_identity)
    refs = [probe.options(scheduling_strategy=NodeAffinitySchedulingStrategy(
        n["NodeID"], soft=False)).remote() for n in alive]
    for node, ref in zip(alive, refs):
        name = node.get("NodeManagerAddress", "?")
        try:
            report = ray.get(ref, timeout=timeout)
        except Exception as e:  # noqa: BLE001 - e.g. ModuleNotFoundError: ftc is not there
            raise RayUnavailable(f"{where}: node {name} cannot run ftc's tasks "
                                 f"({_first_line(e)})") from None
        problem = identity_problem(session.identity, report)
        if problem:
            raise RayUnavailable(f"{where}: {problem}")
        session.nodes.append(report)
    session.cpus = float(ray.cluster_resources().get("CPU", 0.0))


# ---------------------------------------------------------------------------
# The tasks (they run on the nodes)
# ---------------------------------------------------------------------------

class ProgressBoard:
    """A Ray actor the tasks tell their intervals done to (the driver cannot
    read a node's files); the driver reads it for the progress line."""

    def __init__(self) -> None:
        self.counts: dict[str, int] = {}

    def report(self, key: str, intervals: int) -> None:
        self.counts[key] = intervals

    def snapshot(self) -> dict[str, int]:
        return dict(self.counts)


def _report_progress(board: Any, handle: RunHandle, stop: threading.Event) -> None:
    last = -1
    while not stop.wait(1.0):
        if not handle.started:
            continue
        n = count_rows(handle.directory / "controller" / "metrics.csv")
        if n != last:
            board.report.remote(handle.key, n)
            last = n


def _files(root: Path, under: list[Path]) -> dict[str, bytes]:
    """Every file below the ``under`` directories, by path relative to ``root``."""
    # processes.json names this node's pids: meaningless (and unsafe) on the driver's
    return {str(p.relative_to(root)): p.read_bytes() for d in under if d.is_dir()
            for p in sorted(d.rglob("*")) if p.is_file() and p.name != "processes.json"}


def _task_dir(kind: str) -> Path:
    """A new temporary directory for a task, named with this worker's pid; the
    directories of tasks whose worker is gone (killed with its driver, so no
    cleanup ran) are removed first. A live pid's are left alone."""
    root = Path(tempfile.gettempdir())
    for old in root.glob(f"ftc-ray-{kind}-*-*"):
        pid = old.name.split("-")[3]
        if pid.isdigit() and not Path(f"/proc/{pid}").exists():
            shutil.rmtree(old, ignore_errors=True)
    return Path(tempfile.mkdtemp(prefix=f"ftc-ray-{kind}-{os.getpid()}-"))


def run_task(spec: RunSpec, config: ExperimentConfig, scenario_toml: str, identity: dict,
             attempts: int, board: Any, out: str) -> dict:
    """One run on this node, in a temporary directory laid out like OUT; returns
    {"status": "ok" or "failed", "record" or "error", "files" (relative path ->
    bytes, a failed run's too, for diagnosis), "log"}; a message names files by
    their place in the driver's ``out``. A storage error is raised (it stops
    every run). Its processes die with the task (the guardian kills their
    groups when the task ends in any way, ray.cancel included)."""
    here = node_identity()
    problem = identity_problem(identity, here)
    if problem:
        raise RunFailed(problem)
    tmp = _task_dir("run")
    guardian = Guardian()
    handle = RunHandle(spec.key, spec.directory(tmp), guardian=guardian)
    stop = threading.Event()
    reporter = threading.Thread(target=_report_progress, args=(board, handle, stop), daemon=True)
    log = io.StringIO()
    try:
        (tmp / "scenarios").mkdir()
        (tmp / "scenarios" / f"{spec.scenario}.toml").write_text(scenario_toml)
        reporter.start()
        try:
            record = execute_with_retries(spec, config, tmp, handle, attempts, log,
                                          lambda: False)
            record.update(node=here["host"], executor="ray")
            atomic_write_json(handle.directory / RESULT, record)  # says where it ran
            outcome = {"status": "ok", "record": record}
        except StorageError:
            raise
        except Exception as e:  # noqa: BLE001 - a failed run, reported as a local one is
            outcome = {"status": "failed", "error": str(e).replace(str(tmp), out)}
        return {**outcome, "log": log.getvalue().replace(str(tmp), out),
                "files": _files(tmp, [handle.directory, tmp / "failed_attempts"])}
    finally:
        stop.set()
        handle.stop()  # an interrupted task (ray.cancel) stops its processes
        guardian.close()
        shutil.rmtree(tmp, ignore_errors=True)


def baseline_task(stem: str, scenario: str | None, age: int, policy: str,
                  scenario_toml: str | None, identity: dict) -> dict:
    """One baseline episode (figure a) on this node; returns its CSV as bytes."""
    problem = identity_problem(identity, node_identity())
    if problem:
        raise RunFailed(problem)
    tmp = _task_dir("baseline")
    log = io.StringIO()
    try:
        if scenario is not None:
            (tmp / "scenarios").mkdir()
            (tmp / "scenarios" / f"{scenario}.toml").write_text(scenario_toml or "")
        with contextlib.redirect_stderr(log):
            path = run_baseline_episode(tmp, stem, scenario, age, policy)
        return {"files": {str(path.relative_to(tmp)): path.read_bytes()}, "log": log.getvalue()}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


# ---------------------------------------------------------------------------
# The driver
# ---------------------------------------------------------------------------

def write_files(out: Path, key: str | None, files: dict[str, bytes]) -> None:
    """A task's files into OUT, each atomically, result.json last (it marks a
    run finished); a run's earlier, unfinished directory is replaced."""
    out = Path(out)
    root = out.resolve()
    for rel in files:
        if not (root / rel).resolve().is_relative_to(root):
            raise RunFailed(f"a task returned a file outside the run directory: {rel}")
    if key is not None:
        run_dir = out / "runs" / key
        if run_dir.exists():
            stop_leftover_processes(run_dir)  # a local attempt's, killed with its orchestrator
            shutil.rmtree(run_dir)
    for rel in sorted(files, key=lambda r: (Path(r).name == RESULT, r)):
        atomic_write_bytes(out / rel, files[rel])


@dataclass
class _Pending:
    key: str
    run: bool  # a run (else a baseline episode)


def run_on_ray(session: RaySession, out: Path, config: ExperimentConfig, todo: list[RunSpec],
               baselines: list[tuple[str, str | None, int, str]], progress: Progress,
               stream: TextIO, tool: str, attempts: int = 3) -> dict:
    """Run ``todo`` and the baseline episodes as Ray tasks and write their files
    into ``out``; returns key -> {"status", "result" or "error"} like the local
    pool. SIGINT/SIGTERM cancels every task and exits 130, finished runs kept."""
    import ray

    scenarios = out / "scenarios"
    board = ray.remote(num_cpus=0)(ProgressBoard).remote()
    run_remote = ray.remote(num_cpus=1)(run_task)
    base_remote = ray.remote(num_cpus=1)(baseline_task)
    queue: list[tuple[str, bool, Any]] = [
        (f"baseline {s[0]}", False, lambda s=s: base_remote.remote(
            *s, (scenarios / f"{s[1]}.toml").read_text() if s[1] else None, session.identity))
        for s in baselines]
    queue += [(spec.key, True, lambda spec=spec: run_remote.remote(
        spec, config, (scenarios / f"{spec.scenario}.toml").read_text(), session.identity,
        attempts, board, str(out))) for spec in todo]
    queue.reverse()  # popped from the end: baselines first, then the runs most expensive first
    pending: dict[Any, _Pending] = {}
    results: dict[str, dict] = {}
    stopping = threading.Event()
    storage_error: list[StorageError] = []

    def cancel_all() -> None:
        stopping.set()
        queue.clear()
        for ref in pending:
            ray.cancel(ref)

    def on_signal(signum: int, frame: object) -> None:
        cancel_all()
        raise KeyboardInterrupt

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        while queue or pending:
            while queue and (session.jobs is None or len(pending) < session.jobs):
                key, is_run, submit = queue.pop()
                pending[submit()] = _Pending(key, is_run)
            done, _ = ray.wait(list(pending), num_returns=1, timeout=1.0)
            for ref in done:
                task = pending.pop(ref)
                _collect(ray, ref, task, out, results, progress, stream, stopping, storage_error,
                         cancel_all)
            if progress.due():
                counts = ray.get(board.snapshot.remote())
                progress.show_counts({k: n for k, n in counts.items()
                                      if any(t.key == k for t in pending.values())})
        progress.show_counts({}, final=True)
    except KeyboardInterrupt:
        cancel_all()
        ray.wait(list(pending), num_returns=len(pending), timeout=15.0)  # let tasks clean up
        print(f"\n{tool}: interrupted; finished runs are kept, --resume completes the rest",
              file=stream)
        raise SystemExit(130)
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
    if storage_error:
        raise storage_error[0]
    return results


def _collect(ray: Any, ref: Any, task: _Pending, out: Path, results: dict, progress: Progress,
             stream: TextIO, stopping: threading.Event, storage_error: list,
             cancel_all: Any) -> None:
    """One finished task: its files written, its outcome recorded and reported."""
    try:
        value = ray.get(ref)
        if value.get("log"):
            stream.write(value["log"])
        write_files(out, task.key if task.run else None, value["files"])
        if value.get("status", "ok") != "ok":
            raise RunFailed(value["error"])
        results[task.key] = {"status": "ok", "result": value.get("record")}
        if task.run:
            progress.done.add(task.key)
    except StorageError as e:  # the driver's disk, or a node's: stop, as the local pool does
        error = getattr(e, "cause", e)
        results[task.key] = {"status": "failed", "error": str(error)}
        progress.failed.add(task.key)
        if not storage_error:
            storage_error.append(StorageError(str(error)))
            cancel_all()
    except Exception as e:  # noqa: BLE001 - reported per run, the rest go on
        error = getattr(e, "cause", None) or e
        message = str(error) if isinstance(error, RunFailed) else _first_line(error)
        results[task.key] = {"status": "failed", "error": message}
        progress.failed.add(task.key)
        if not stopping.is_set():
            stream.write(f"\n{task.key}: FAILED: {message}\n")
