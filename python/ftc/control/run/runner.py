"""The interval runner: the one loop every controller runs in.

    python -m ftc.controller ...   (PPO, baselines)     python -m ftc.mpc ...   (MPC)

One interval k (t_online real steps; the plant degrades itself at each
interval boundary and ends episodes itself):

    plant --obs--> agent.act --valves--> plant      x steps_per_interval
      |               ^                               (reset after a terminal step)
      +-- reward, Transition --> agent.observe        (PPO: update every t_update)
      |
      +-- evaluation episode (age frozen), agent.act(evaluation)   if agent.evaluates
      |   bounded at steps_per_interval steps (a dead pump can strand fuel forever)
      |
      +-- Transitions of the interval --> agent.end_interval      (refit, offline, swap)
      |
    metrics.csv row, checkpoint.pt, progress line

The runner owns the plant link, the loop and its checks, metrics.csv,
config.json, checkpoints and --resume, done.json and the progress lines; the
agent (:mod:`ftc.control.run.agent`) owns its decisions and what it learns.

Failures raise :class:`ftc.common.errors.RunError` subclasses (their
``exit_code`` is the command line's), with nothing written after the last
finished interval, so metrics.csv and checkpoint.pt stay those of that
interval and --resume continues from it.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import Any, Iterator

import torch

from ftc.common.atomic import atomic_write_csv, atomic_write_json, atomic_write_text
from ftc.common.build_info import ftc_version, git_revision
from ftc.common.errors import CheckpointError, PlantLostError, UsageError
from ftc.common.replacing import Replacement
from ftc.common.run_lock import RunLock
from ftc.control.run import checkpoint
from ftc.control.run.agent import Agent
from ftc.control.run.config import RUN_FILES, RunConfig, open_plant
from ftc.control.run.lockstep import LockstepLoop
from ftc.control.run.metrics import format_cell, metric_columns, progress_line
from ftc.control.run.policy_weights import PUSH_COLUMNS, push_policy
from ftc.control.run.realtime import REALTIME_COLUMNS, RealtimeLoop
from ftc.control.run.telemetry import NULL_TELEMETRY, Telemetry, open_telemetry
from ftc.learning.transitions import Transitions
from ftc.plant.link import ForeignTrafficError, PlantGoneError, PlantLink
from ftc.plant.signing import load_key


@contextlib.contextmanager
def _driving(plant: PlantLink, out: Path) -> Iterator[None]:
    """The block drives ``plant``, which is closed after it whatever happens;
    OUT/plant.pid names a launched plant's process meanwhile (for tools and
    tests that need it) and is removed even if closing fails."""
    pid_file = out / "plant.pid"
    process = getattr(plant, "process", None)
    if process is not None:
        atomic_write_text(pid_file, f"{process.pid}\n")
    try:
        yield
    finally:
        try:
            plant.close()
        finally:
            if process is not None:
                pid_file.unlink(missing_ok=True)


def _checkpointed(out: Path) -> bool:
    return (out / "checkpoint.pt").exists()


def replacement(out: Path) -> Replacement:
    """--overwrite of the run in ``out``: proven by its first checkpoint."""
    return Replacement(out, RUN_FILES, _checkpointed)


@contextlib.contextmanager
def _owning(out: Path, cfg: RunConfig, tool: str) -> Iterator[None]:
    """The block writes the run in ``out`` as its only writer (OUT/run.lock; a
    live holder raises InUse, a stale one is taken over with a note). A new
    run refuses a directory holding a run unless cfg.overwrite, which moves
    the old one aside until the new one's first checkpoint (the runner's
    checkpoint() then deletes it). A new run that fails before its first
    checkpoint leaves the directory as it found it: what it wrote removed,
    a replaced run moved back."""
    lock = RunLock(out, tool).acquire()
    try:
        lock.announce_takeover()
        fresh = not cfg.resume
        if fresh:
            held = run_files_held(out)
            if held and not cfg.overwrite:
                raise UsageError(held_advice(out, held))
            replacement(out).stash_old()
        try:
            yield
        except BaseException:
            if fresh and not _checkpointed(out):  # failed before its first interval
                replaced = replacement(out)
                if replaced.pending():
                    replaced.restore()
                else:
                    for name in RUN_FILES:
                        (out / name).unlink(missing_ok=True)
            raise
    finally:
        lock.release()


def held_advice(out: Path, held: str) -> str:
    """Why a new run (no --overwrite, no --resume) refuses ``out``, which holds
    ``held``, and the command that goes on: a run that never finished an
    interval (one killed there, an --overwrite among them) has nothing to
    resume, so --overwrite starts it again."""
    if _checkpointed(out):
        return f"{out} already holds a run ({held}): --resume {out} continues it, " \
               "--overwrite replaces it"
    return (f"{out} holds a run that stopped before its first interval finished ({held}): "
            "nothing to resume; --overwrite starts it again")


def settle_metrics(path: Path, rows: list[dict[str, Any]], columns: list[str],
                   tool: str) -> None:
    """A finished run's metrics.csv made its checkpoint's ``rows`` again where
    they disagree (a stray or a missing row), saying so: the checkpoint is
    what the run did. The file's own header is kept (a real-time run's columns)."""
    try:
        with open(path, newline="") as f:
            table = list(csv.reader(f))
    except (OSError, UnicodeDecodeError, csv.Error):
        table = []
    header = table[0] if table and table[0][:1] == ["interval"] else columns
    if [r[:1] for r in table[1:]] == [[str(row["interval"])] for row in rows]:
        return
    atomic_write_csv(path, header, [[format_cell(row.get(c)) for c in header] for row in rows],
                     lineterminator="\n")
    print(f"{tool}: {path} did not match the run's checkpoint ({max(len(table) - 1, 0)} rows "
          f"for {len(rows)} intervals): rewritten from the checkpoint", flush=True)


def run_files_held(out: Path) -> str | None:
    """What makes ``out`` hold a run (its files, or a replaced run waiting), or None."""
    held = [n for n in RUN_FILES if (out / n).exists()]
    if replacement(out).pending():
        held.append(f"a replaced run in {out / '.replaced'}")
    return ", ".join(held) or None


def record_extension(out: Path, parts: list[str], intervals: int) -> bool:
    """A resumed run asked for more intervals than its config.json says: record
    the new count there (a later --resume continues to it) and mark the run
    unfinished again. Returns whether it was extended."""
    path = out / "config.json"
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise CheckpointError(f"{path}: unreadable ({e})") from None
    parts = [p for p in parts if isinstance(doc.get(p), dict) and "intervals" in doc[p]]
    if not parts or all(doc[p]["intervals"] == intervals for p in parts):
        return False
    before = doc[parts[0]]["intervals"]
    for p in parts:
        doc[p]["intervals"] = intervals
    doc.setdefault("extended", []).append({"from": before, "to": intervals, "argv": sys.argv})
    atomic_write_json(path, doc)
    (out / "done.json").unlink(missing_ok=True)
    return True


class IntervalRunner:
    """Runs ``agent`` on the plant of ``cfg`` interval by interval.

    configs: the config dataclasses of the run by name ({"controller": ...,
    "ppo": ...}); they go into config.json and a checkpoint must match them.
    """

    tool = "ftc.controller"  # the command line that runs it: messages, the lock's record

    def __init__(self, cfg: RunConfig, agent: Agent, configs: dict[str, Any]) -> None:
        self.cfg, self.agent, self.configs = cfg, agent, configs
        self.out = Path(cfg.out)
        self.rows: list[dict[str, Any]] = []
        self.info: dict[str, Any] = {}
        self.interval = 0
        self.saved = 0  # intervals in the last checkpoint (a real-time fit may still run)
        self.telemetry: Telemetry = NULL_TELEMETRY  # --tensorboard: opened by run()
        self.columns = metric_columns(agent.extra_columns)
        self.loop: LockstepLoop | RealtimeLoop = LockstepLoop(None, agent, NULL_TELEMETRY)

    # -- the run ----------------------------------------------------------------
    def run(self, stop_after: int | None = None, plant: PlantLink | None = None
            ) -> list[dict[str, Any]]:
        """Run (or continue, with cfg.resume) the intervals as the only writer
        of the run directory (:func:`_owning`); returns the metrics rows.

        stop_after: return after this many intervals of this call, as if the run
        had been stopped there (its checkpoint written; for tests of --resume).
        plant: drive this link instead of opening one from the config (tests).
        """
        with _owning(self.out, self.cfg, self.tool):
            cfg = self.cfg
            # one intra-op thread: tiny networks, and bit-for-bit reproducible results
            # (measured: with the default pool, losses differ in the 7th digit run to run)
            torch.set_num_threads(1)
            torch.manual_seed(cfg.seed)
            if cfg.resume:
                self.restore()
                if self.interval >= cfg.intervals:
                    settle_metrics(self.out / "metrics.csv", self.rows, self.columns, self.tool)
                    print(f"{self.tool}: {self.out} has finished its {self.interval} intervals; "
                          f"nothing to do (--intervals N above {self.interval} extends it)",
                          flush=True)
                    return self.rows
                if record_extension(self.out, list(self.configs), cfg.intervals):
                    self._say(f"extending {self.out} to {cfg.intervals} intervals")
            else:
                if getattr(cfg, "push_policy", None) and self.agent.exported_policy() is None:
                    raise UsageError(f"--push-policy: {self.agent.name} has no policy to push "
                                     "(the PPO methods have)")
                self.write_config()
                self.info.update(self.agent.prepare())
                self._say(" ".join(f"{k}={v:.4g}" for k, v in self.info.items()))
            start = time.perf_counter()
            try:
                self.telemetry = self.agent.telemetry = open_telemetry(
                    cfg.tensorboard, cfg.steps_per_interval, self.interval if cfg.resume else None)
                if plant is None:
                    try:
                        plant = open_plant(cfg, self.interval * cfg.steps_per_interval)
                    except PlantLostError as e:
                        raise PlantLostError(f"at interval {self.interval}: {e}") from None
                self._run_intervals(plant, start, stop_after)
            except PlantGoneError as e:
                what = "stopped" if isinstance(e, ForeignTrafficError) else "plant gone"
                raise PlantLostError(f"{what} at {self.loop.where}: {e}; results of the "
                                     f"{self.saved} finished intervals are in {self.out}, "
                                     "--resume continues from them") from None
            finally:
                self.agent.close()
                self.telemetry.close()
            if self.interval >= cfg.intervals:
                done = {"intervals": self.interval, "wall_time": time.perf_counter() - start}
                atomic_write_json(self.out / "done.json", done, indent=None)
            return self.rows

    def _run_intervals(self, plant: PlantLink, start: float, stop_after: int | None) -> None:
        if getattr(plant, "realtime", False):
            self.loop = RealtimeLoop(plant, self.agent, self.telemetry)
            self.agent.background_learning = True
            self.columns = metric_columns((*self.agent.extra_columns, *REALTIME_COLUMNS))
        else:
            self.loop = LockstepLoop(plant, self.agent, self.telemetry)
        with _driving(plant, self.out):
            while self.interval < self.cfg.intervals:
                self._one_interval(plant, start)
                if stop_after is not None and self.interval >= stop_after:
                    return
            self.agent.finish()
            self._merge_late_metrics()
            self.checkpoint()
            self.write_metrics()
            if isinstance(self.loop, RealtimeLoop) and (note := self.loop.foreign_note()):
                print(f"{self.tool}: warning: {note}", file=sys.stderr, flush=True)

    def _one_interval(self, plant: PlantLink, start: float) -> None:
        k = self.interval
        t0 = time.perf_counter()
        self.agent.begin_interval(k)
        self.telemetry.begin_interval(k)
        online, data = self.online(plant)
        row = {"interval": k, **online, "online_seconds": time.perf_counter() - t0}
        row["eval_reward_per_step"], row["eval_steps"] = (
            self.evaluate(plant) if self.agent.evaluates else (None, None))
        if getattr(plant, "lockstep_checks", False):  # no step of the interval was raced:
            plant.hello()  # the lockstep link raises ForeignTrafficError if one was
        if isinstance(self.loop, RealtimeLoop):
            row.update(self.loop.deadline_row())
            if k + 1 < self.cfg.intervals:  # the plant does not wait for the bookkeeping
                self.loop.open_next(k + 1, self.cfg.steps_per_interval)
        self.rows.append(row)
        row.update(self.agent.end_interval(k, data))
        self._merge_late_metrics()
        row["wall_time"] = time.perf_counter() - start
        self.interval += 1
        if self.agent.learning:  # real time: the fit runs on; saved once it is done,
            self.agent.on_learned = lambda _: self._save()  # before the next interval's steps
        else:
            self._save()
        self.telemetry.end_interval(row)
        self._say(progress_line(row, self.cfg.intervals, self.agent.progress_keys))

    def _save(self) -> None:
        """The finished intervals' checkpoint and metrics.csv (and the policy pushed)."""
        self._merge_late_metrics()
        if getattr(self.cfg, "push_policy", None):  # the controller's option
            key_file = getattr(self.cfg, "push_key_file", None)
            pushed = push_policy(self.agent.exported_policy(), self.cfg.push_url,
                                 self.cfg.push_policy, load_key(key_file) if key_file else None)
            self.rows[self.interval - 1].update(  # 1 accepted, 0 rejected, '' no answer
                push_version=pushed.version, push_reason=pushed.reason,
                push_accepted=None if pushed.accepted is None else int(pushed.accepted))
            self.columns += [c for c in PUSH_COLUMNS if c not in self.columns]
            if not pushed.accepted:
                print(f"warning: policy push after interval {self.interval - 1} to "
                      f"{self.cfg.push_policy}POLICY: {pushed.describe()}", file=sys.stderr)
        self.checkpoint()
        self.write_metrics()

    def _merge_late_metrics(self) -> None:
        for interval, metrics in self.agent.late_metrics():
            self.rows[interval].update(metrics)
            self.telemetry.late(interval, metrics)

    def online(self, plant: PlantLink) -> tuple[dict[str, Any], Transitions | None]:
        """One interval of operating steps; returns its metrics and, for an agent
        that wants them, its transitions."""
        keep = self.agent.wants_data()
        metrics, observations = self.loop.online(self.interval, self.cfg.steps_per_interval, keep)
        return metrics, (Transitions.from_observations(observations) if keep else None)

    def evaluate(self, plant: PlantLink) -> tuple[float, int]:
        """One evaluation episode (age frozen; a learned policy acts greedily),
        cut off after steps_per_interval steps: fuel stranded behind a dead pump
        can keep an episode from ever ending. Returns (reward per step, steps)."""
        return self.loop.evaluate(self.interval, self.cfg.steps_per_interval)

    # -- persistence -------------------------------------------------------------
    def checkpoint(self) -> None:
        """Everything needed to continue after interval ``self.interval - 1``;
        a run replaced by --overwrite is deleted once this one has saved one."""
        checkpoint.save(self.out / "checkpoint.pt", {
            "interval": self.interval, "rows": self.rows, "info": self.info,
            "torch_rng": torch.get_rng_state(), "config": checkpoint.config_stamp(self.configs),
            "agent": self.agent.state_dict()})
        self.saved = self.interval
        replacement(self.out).commit()

    def restore(self) -> None:
        path = self.out / "checkpoint.pt"
        state = checkpoint.load(path, self.configs, self.cfg.intervals)
        self.interval, self.rows, self.info = state["interval"], state["rows"], state["info"]
        self.saved = self.interval
        torch.set_rng_state(state["torch_rng"])
        try:
            self.agent.load_state_dict(state["agent"])
        except CheckpointError as e:
            raise CheckpointError(f"{path}: {e}") from None
        except (KeyError, RuntimeError, ValueError, TypeError) as e:
            reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise CheckpointError(f"{path}: the {self.agent.name} state does not load: "
                                  f"{reason[:200]}") from None

    def write_metrics(self) -> None:
        atomic_write_csv(self.out / "metrics.csv", self.columns,
                         [[format_cell(row.get(c)) for c in self.columns] for row in self.rows],
                         lineterminator="\n")

    def write_config(self) -> None:
        doc = {**{name: dataclasses.asdict(c) for name, c in self.configs.items()},
               "seed": self.cfg.seed, "git_revision": git_revision(),
               "ftc_version": ftc_version(), "argv": sys.argv,
               **self.agent.config_doc()}
        atomic_write_json(self.out / "config.json", doc)

    def _say(self, text: str) -> None:
        if not self.cfg.quiet and text:
            print(text, flush=True)
