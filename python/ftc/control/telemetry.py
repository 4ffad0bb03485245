"""Telemetry of interval runs: TensorBoard scalars (``--tensorboard DIR``), or
nothing.

The runner and the agents call the hooks of a :class:`Telemetry`
unconditionally; without --tensorboard it is the base class, whose hooks do
nothing (one no-op method call per step), so the default path costs nothing
and imports no TensorBoard. :class:`TensorBoardTelemetry` writes, with
``torch.utils.tensorboard.SummaryWriter``, every scalar against the run's
operating steps (the x-axis every tag shares: interval k's own scalars sit at
step (k + 1) x steps_per_interval, the end of the interval):

    update/<stat>             every PPO update: entropy, approx_kl, clipfrac,
                              explained_variance, value_loss, policy_loss,
                              open_fraction, gradient_steps (learning.ppo.UpdateStats)
    interval/<column>         every numeric metrics.csv column of the interval
                              (reward_per_step, eval_reward_per_step, model_r2,
                              model_one_step_rmse, ... as in the CSV, 6 digits there)
    reward/<term>             the interval's mean reward terms (plant.reward):
                              balance = (1 - |cg| / 3) x spread, activity (the open
                              valve fraction), abs_cg, spread; reward = balance - activity
    time/steps_per_second     operating steps per second of the interval's online phase

Missing and nan values (a blank metrics.csv cell) are not written. Event files
are append-only logs, the one kind of output not written atomically: they are
flushed after every interval, and a resumed run purges (``purge_step``) what
an interrupted interval had written past the checkpoint.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ftc.common.errors import StorageError
from ftc.plant.reward import reward_terms


class Telemetry:
    """The hooks every run calls; this base class does nothing (no --tensorboard).

    Per interval k the runner calls ``begin_interval(k)``, ``step(level, valves)``
    after every operating step, ``end_interval(row)`` with the metrics.csv row,
    and ``late(k, metrics)`` for metrics of an earlier interval arriving later
    (a background offline phase). Agents call ``update(stats)`` after every PPO
    update (stats: field name -> number)."""

    def begin_interval(self, interval: int) -> None:
        """Interval ``interval`` starts (operating step interval x steps_per_interval)."""

    def step(self, level: np.ndarray, valves: np.ndarray) -> None:
        """One operating step: levels after it (6,) m, the valves applied (6,) {0, 1}."""

    def update(self, stats: Mapping[str, float]) -> None:
        """One PPO update's statistics, at the current operating step."""

    def end_interval(self, row: Mapping[str, Any]) -> None:
        """The interval's metrics.csv row (the interval is over)."""

    def late(self, interval: int, metrics: Mapping[str, Any]) -> None:
        """Metrics of an earlier interval that arrived since."""

    def close(self) -> None:
        """Flush and release the files; called once, also on failure."""


def _number(value: Any) -> float | None:
    """``value`` as a float for a scalar, or None (missing, nan, not a number)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
        return None
    x = float(value)
    return None if math.isnan(x) else x


class TensorBoardTelemetry(Telemetry):
    """Scalars into a TensorBoard event file in ``log_dir`` (see the module doc).

    steps_per_interval: operating steps per interval (the x-axis);
    purge_step: on resume, the first operating step the run writes again:
    events at or after it, written by the interrupted run, are hidden."""

    def __init__(self, log_dir: str | Path, steps_per_interval: int,
                 purge_step: int | None = None) -> None:
        # optional and heavy (TensorBoard, protobuf): imported only when asked for
        from torch.utils.tensorboard import SummaryWriter

        self.log_dir = Path(log_dir)
        self.steps_per_interval = steps_per_interval
        self.global_step = 0
        self._levels: list[np.ndarray] = []
        self._valves: list[np.ndarray] = []
        try:
            self.writer = SummaryWriter(log_dir=str(self.log_dir), purge_step=purge_step)
        except OSError as e:
            raise StorageError(f"--tensorboard {self.log_dir}: {e.strerror or e}") from None

    def _scalar(self, tag: str, value: Any, step: int) -> None:
        x = _number(value)
        if x is not None:
            try:
                self.writer.add_scalar(tag, x, step)
            except OSError as e:  # the writer's thread failed (disk full)
                raise StorageError(f"cannot write TensorBoard events in {self.log_dir}: "
                                   f"{e.strerror or e}") from None

    def begin_interval(self, interval: int) -> None:
        self.global_step = interval * self.steps_per_interval
        self._levels, self._valves = [], []

    def step(self, level: np.ndarray, valves: np.ndarray) -> None:
        self.global_step += 1
        self._levels.append(np.array(level, dtype=np.float64))
        self._valves.append(np.array(valves, dtype=np.float64))

    def update(self, stats: Mapping[str, float]) -> None:
        for name, value in stats.items():
            self._scalar(f"update/{name}", value, self.global_step)

    def _interval_step(self, interval: int) -> int:
        return (interval + 1) * self.steps_per_interval

    def end_interval(self, row: Mapping[str, Any]) -> None:
        step = self._interval_step(int(row["interval"]))
        for name, value in row.items():
            if name != "interval":
                self._scalar(f"interval/{name}", value, step)
        if self._levels:
            terms = reward_terms(np.array(self._levels), np.array(self._valves))
            for name, values in (("reward", terms.reward), ("balance", terms.balance),
                                 ("activity", terms.activity), ("abs_cg", np.abs(terms.cg)),
                                 ("spread", terms.spread)):
                self._scalar(f"reward/{name}", float(np.mean(values)), step)
        seconds = _number(row.get("online_seconds"))
        if seconds:
            self._scalar("time/steps_per_second", len(self._levels) / seconds, step)
        self.flush()

    def late(self, interval: int, metrics: Mapping[str, Any]) -> None:
        for name, value in metrics.items():
            self._scalar(f"interval/{name}", value, self._interval_step(interval))
        self.flush()

    def flush(self) -> None:
        try:
            self.writer.flush()
        except OSError as e:
            raise StorageError(f"cannot write TensorBoard events in {self.log_dir}: "
                               f"{e.strerror or e}") from None

    def close(self) -> None:
        try:
            self.writer.close()
        except OSError as e:
            raise StorageError(f"cannot write TensorBoard events in {self.log_dir}: "
                               f"{e.strerror or e}") from None


NULL_TELEMETRY = Telemetry()


def open_telemetry(log_dir: str | None, steps_per_interval: int,
                   resumed_at: int | None = None) -> Telemetry:
    """TensorBoard telemetry into ``log_dir``, or the null one when it is None.

    resumed_at: the interval a resumed run continues from; what the interrupted
    run wrote after that interval's first operating step is purged."""
    if log_dir is None:
        return NULL_TELEMETRY
    purge = None if resumed_at is None else resumed_at * steps_per_interval + 1
    return TensorBoardTelemetry(log_dir, steps_per_interval, purge)
