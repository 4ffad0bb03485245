"""adaptive-policy's online fine-tune (``--fine-tune``; docs/adaptive.md):
expert iteration around the student, on a model learned from the plant's own
steps, off the control loop. No plant equations: this module is a source of
the import contract "learned-no-equations" (pyproject.toml), as the agent is.

* **The learned model** is learned-mpc's (:class:`ftc.learning.feature_model.FeatureModel`,
  its defaults): fitted on nominal data before interval 0 (:func:`fit_nominal`),
  then updated after every step on the plant, the valves seen stuck tracked
  (:func:`learn_step`).
* **The online teacher** rates, after each interval, every state the student
  acted on in it: the 64 settings, each as "hold ``hold`` steps then all
  closed" over ``horizon`` steps (the plans of the student's own teacher),
  rolled out on the learned model (:class:`LearnedEvaluator`).
* **The labels**: among the student's ``candidates`` most probable settings
  (its choice and the next, by default: the model only arbitrates between
  settings the student already weighs), where the model rates the best above
  the student's own choice by more than ``margin`` (summed reward over the
  horizon), that setting; elsewhere the student's own choice (a replay of its
  decisions, so it does not forget what it is not corrected on).
* **The fine-tune**: the labelled windows of the last ``memory`` states (the
  interval's and earlier ones), ``epochs`` passes of Adam at ``lr`` on the
  cross entropy of the labels (:func:`fine_tune`), on a copy of the student
  that replaces the acting one once it is done. The acting is unchanged: one
  forward pass per step.

:class:`OnlineTeacher` keeps the model and the interval's states; its
:meth:`OnlineTeacher.job` is the piece of learning the agent runs between
intervals, or on a worker thread on a real-time plant.
"""

from __future__ import annotations

import copy
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import torch

from ftc.common.constants import NUM_TANKS
from ftc.common.errors import CheckpointError
from ftc.control.agents.learned.learned_mpc import (LearnedEvaluator, LearnedMPCConfig,
                                                   error_metrics, fit_nominal, learn_step)
from ftc.control.planning.planners import hold_candidates
from ftc.control.run.agent import Transition
from ftc.learning.feature_model import FeatureModel
from ftc.learning.history_policy import HistoryPolicy
from ftc.learning.stuck import StuckValves

MODEL = LearnedMPCConfig()  # the learned model as learned-mpc's defaults configure it
BITS = 1 << np.arange(NUM_TANKS)  # valve i open <-> bit i of the setting's code
RATED_PER_BATCH = 64  # states rolled out on the model in one batch (64 x 64 plans)


@dataclass(frozen=True)
class FineTuneSettings:
    """margin: summed reward over the horizon by which the model's best setting
    must beat the student's choice to become its label; candidates: how many
    settings may be labels, the student's most probable ones (64: all);
    lr, epochs, batch:
    Adam's fit on the labels; memory: labelled states kept (the newest);
    hold, horizon: the rated plans; seed: the minibatch order."""

    margin: float = 0.5
    candidates: int = 2
    lr: float = 1e-4
    epochs: int = 4
    batch: int = 128
    memory: int = 2048
    hold: int = 3
    horizon: int = 10
    seed: int = 0


def setting_codes(valves: np.ndarray) -> np.ndarray:
    """The setting code (0..63) of valves (..., 6)."""
    return (np.asarray(valves, np.int64) * BITS).sum(-1)


def rate_settings(evaluate: Callable[[np.ndarray, np.ndarray], np.ndarray],
                  levels: np.ndarray, hold: int, horizon: int) -> np.ndarray:
    """Summed reward (S, 64) of each setting held ``hold`` steps then all closed,
    over ``horizon`` steps from each of the levels (S, 6), by ``evaluate``
    (a :class:`LearnedEvaluator`: its start levels may be one row per plan)."""
    plans = hold_candidates(hold, horizon)
    out = np.zeros((len(levels), len(plans)))
    for i in range(0, len(levels), RATED_PER_BATCH):
        chunk = np.asarray(levels[i:i + RATED_PER_BATCH], np.float64)
        starts = np.repeat(chunk, len(plans), axis=0)
        out[i:i + len(chunk)] = evaluate(starts, np.tile(plans, (len(chunk), 1, 1))
                                         ).reshape(len(chunk), len(plans))
    return out


def corrected_labels(totals: np.ndarray, chosen: np.ndarray, margin: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """(labels (S,), corrected (S,) bool): the best-rated setting (the first on
    ties) where it beats the chosen one by more than ``margin``, else the choice."""
    best = totals.argmax(axis=1)
    gain = totals[np.arange(len(totals)), best] - totals[np.arange(len(totals)), chosen]
    corrected = gain > margin
    return np.where(corrected, best, chosen), corrected


@torch.no_grad()
def setting_log_probs(policy: HistoryPolicy, features: np.ndarray) -> np.ndarray:
    """log-probability (S, 64) the student gives each setting on windows (S, F):
    the joint head's softmax, or the product of the valves head's six sigmoids."""
    logits = policy(torch.as_tensor(np.asarray(features, np.float32)))
    if policy.config.head == "joint":
        return torch.log_softmax(logits, dim=1).numpy()
    bits = torch.as_tensor(((np.arange(2 ** NUM_TANKS)[:, None] >> np.arange(NUM_TANKS)) & 1)
                           * 2.0 - 1.0, dtype=logits.dtype)  # (64, 6): +1 open, -1 closed
    return torch.nn.functional.logsigmoid(logits[:, None, :] * bits).sum(-1).numpy()


def likeliest_only(totals: np.ndarray, log_probs: np.ndarray, chosen: np.ndarray, k: int
                   ) -> np.ndarray:
    """``totals`` (S, 64) with every setting but the student's ``k`` most probable
    (by ``log_probs``, its choice ``chosen`` always among them) rated -inf: the
    learned model only arbitrates between settings the student already weighs."""
    rank = np.array(log_probs, np.float64, copy=True)
    rank[np.arange(len(chosen)), chosen] = np.inf
    out = np.array(totals, np.float64, copy=True)
    np.put_along_axis(out, np.argsort(-rank, axis=1, kind="stable")[:, k:], -np.inf, axis=1)
    return out


def fine_tune(policy: HistoryPolicy, features: np.ndarray, labels: np.ndarray, *, lr: float,
              epochs: int, batch: int, seed: int) -> float:
    """Fit ``policy`` in place toward the settings ``labels`` (S,) on windows
    ``features`` (S, F): ``epochs`` passes of Adam at ``lr``, minibatches of
    ``batch`` in a seeded order; cross entropy of the setting with the joint
    head, binary cross entropy of its six bits with the valves head. Returns
    the last epoch's mean loss."""
    x = torch.as_tensor(np.asarray(features, np.float32))
    y = torch.as_tensor(np.asarray(labels, np.int64))
    bits = ((y[:, None] >> torch.arange(NUM_TANKS)) & 1).float()
    joint = policy.config.head == "joint"
    gen = torch.Generator().manual_seed(seed)
    opt = torch.optim.Adam(policy.parameters(), lr=lr)
    policy.train()
    loss_sum = 0.0
    for _ in range(epochs):
        loss_sum = 0.0
        for b in torch.randperm(len(x), generator=gen).split(batch):
            logits = policy(x[b])
            loss = (torch.nn.functional.cross_entropy(logits, y[b]) if joint else
                    torch.nn.functional.binary_cross_entropy_with_logits(logits, bits[b]))
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            loss_sum += float(loss.detach()) * len(b)
    policy.eval()
    return loss_sum / max(1, len(x))


class OnlineTeacher:
    """The learned model, the interval's states and the labelled memory; see the module."""

    def __init__(self, settings: FineTuneSettings) -> None:
        self.settings = settings
        self.model = FeatureModel(MODEL.learn_features, MODEL.learn_forget, MODEL.learn_ridge,
                                  seed=settings.seed)
        self.demand = 0.0
        self.stuck = StuckValves()
        self.errors: list[np.ndarray] = []
        self.memory_x = np.zeros((0, 0), np.float32)  # labelled windows, oldest first
        self.memory_y = np.zeros(0, np.int64)  # their settings
        self.memory_c = np.zeros(0, bool)  # which of them the model corrected
        self.tunes = 0
        self._new_interval()

    def _new_interval(self) -> None:
        self.windows: list[np.ndarray] = []  # (F,) each: what the student acted on
        self.levels: list[np.ndarray] = []
        self.chosen: list[int] = []

    def prepare(self) -> dict[str, Any]:
        self.demand, info = fit_nominal(self.model, MODEL.learn_episodes, self.settings.seed)
        return info

    def record(self, window: np.ndarray, level: np.ndarray, valves: np.ndarray) -> None:
        """A decision on the plant: the student's window (F,), the levels, its valves."""
        self.windows.append(np.asarray(window, np.float32))
        self.levels.append(np.asarray(level, np.float64))
        self.chosen.append(int(setting_codes(valves)))

    def observe(self, t: Transition) -> None:
        self.demand = learn_step(self.model, t, self.stuck, self.errors, self.demand)

    def job(self, policy: HistoryPolicy) -> Callable[[], tuple[HistoryPolicy, dict[str, Any]]]:
        """The interval's learning, on copies of the model and the student: rate
        the interval's states, label them, fine-tune on the memory. Returns a
        function giving (the tuned student, its metrics), to run now or on a
        worker; the memory is updated when it is called."""
        self.model.settle()
        model, stuck = copy.deepcopy(self.model), dict(self.stuck.stuck)
        demand, s = self.demand, self.settings
        windows = np.array(self.windows, np.float32).reshape(len(self.windows), -1)
        levels = np.array(self.levels).reshape(-1, NUM_TANKS)
        chosen = np.array(self.chosen, np.int64)
        seed, student = s.seed + 1000 * self.tunes, copy.deepcopy(policy)
        metrics = {"model_one_step_rmse": error_metrics(self.errors)["model_one_step_rmse"],
                   **self.stuck.metrics()}
        self.tunes += 1
        self.errors = []
        self._new_interval()

        def run() -> tuple[HistoryPolicy, dict[str, Any]]:
            t0 = time.perf_counter()
            evaluate = LearnedEvaluator(model, demand, MODEL.learn_terminal_band, stuck)
            totals = rate_settings(evaluate, levels, s.hold, s.horizon)
            if s.candidates < totals.shape[1] and len(levels):
                totals = likeliest_only(totals, setting_log_probs(student, windows), chosen,
                                        s.candidates)
            labels, corrected = corrected_labels(totals, chosen, s.margin)
            self._remember(windows, labels, corrected)
            loss = float("nan")  # nothing corrected in the memory: the student is kept
            if self.memory_c.any() and s.epochs:
                with torch.enable_grad():
                    loss = fine_tune(student, self.memory_x, self.memory_y, lr=s.lr,
                                     epochs=s.epochs, batch=s.batch, seed=seed)
            return student, {**metrics, "fine_tune_states": len(levels),
                             "fine_tune_corrected": int(corrected.sum()),
                             "fine_tune_loss": loss,
                             "fine_tune_seconds": time.perf_counter() - t0}
        return run

    def _remember(self, windows: np.ndarray, labels: np.ndarray, corrected: np.ndarray) -> None:
        if not len(windows):
            return
        if not self.memory_y.size:
            self.memory_x = np.zeros((0, windows.shape[1]), np.float32)
        keep = self.settings.memory
        self.memory_x = np.concatenate([self.memory_x, windows])[-keep:]
        self.memory_y = np.concatenate([self.memory_y, labels])[-keep:]
        self.memory_c = np.concatenate([self.memory_c, corrected])[-keep:]

    # -- persistence -------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        return {"learned_model": self.model.state_dict(), "demand": self.demand,
                "stuck_valves": self.stuck.state_dict(), "tunes": self.tunes,
                "memory_x": torch.as_tensor(self.memory_x),
                "memory_y": torch.as_tensor(self.memory_y),
                "memory_c": torch.as_tensor(self.memory_c)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        missing = sorted({"learned_model", "demand", "stuck_valves", "tunes", "memory_x",
                          "memory_y", "memory_c"} - set(state))
        if missing:
            raise CheckpointError(f"checkpoint lacks the fine-tune's {', '.join(missing)}")
        self.model.load_state_dict(state["learned_model"])
        self.demand, self.tunes = float(state["demand"]), int(state["tunes"])
        self.stuck.load_state_dict(state["stuck_valves"])
        self.memory_x = state["memory_x"].numpy().astype(np.float32)
        self.memory_y = state["memory_y"].numpy().astype(np.int64)
        self.memory_c = state["memory_c"].numpy().astype(bool)
