"""The adaptive student: a policy that acts on the recent history of what a
deployed controller sees (published levels and its own valve commands), in
one forward pass per step, with no plant equations (docs/adaptive.md).

Input: a window of the last ``window`` steps, newest first, each step the six
levels (m) and the six valves commanded after them, scaled to [-1, 1]
(``2 x - 1``), flattened to ``12 * window`` floats. At an episode's start the
window is filled with the first levels and closed valves, so the policy sees
a plant that has just been reset. Network: tanh MLP to logits; the default
"joint" head has 64, one per valve setting, and applies the setting a of the
largest logit (the first on ties), valve i open iff bit i of a is set; the
"valves" head has six, a valve opening where its logit is positive (the
deployed policies' rule, cpp/policy/policy.h).

:class:`HistoryWindow` keeps N windows at once (the batched pool, N = 1 in a
controller); :class:`HistoryPolicy` is the network.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from ftc.common.constants import NUM_TANKS, NUM_VALVES
from ftc.common.source_key import closure_digest, native_source_digest
from ftc.learning.stuck import StuckMemory

STEP_FEATURES = 2 * NUM_TANKS  # levels and valves of one step
STUCK_FEATURES = 2 * NUM_VALVES  # the stuck memory: per valve seen stuck closed, then open
# the module whose import closure trains the checkpoint (its code is the cache key's);
# named, not imported: this module stays free of the plant equations training uses
TRAINER = "ftc.experiments.adaptive.dagger"
CACHE_VERSION = 1  # bump when the checkpoint record's layout changes
HEADS = {"valves": NUM_TANKS, "joint": 2 ** NUM_TANKS}  # outputs of each head
INPUTS = ("window", "rates")  # the training-time input parametrizations (TrainingConfig.inputs)
TEACHER_STUCK = ("all", "seen")  # which stuck valves the teacher plans with (TrainingConfig)
RECHECK_RULES = ("closed", "balance", "best")  # after a rechecked hold (TrainingConfig, teacher)


@dataclass(frozen=True)
class StudentConfig:
    """The student's architecture.

    window: steps of history in its input (1: the current levels and the last
        valves only); hidden: widths of its tanh layers; head: "valves" (six
        logits, valve i opens where logit i > 0) or "joint" (64 logits, one per
        valve setting: the setting a of the largest logit, first on ties, opens
        valve i iff bit i of a is set); stuck_memory: 12 more inputs, the valves
        seen stuck (:class:`HistoryWindow`)."""

    window: int = 12
    hidden: tuple[int, ...] = (128, 128)
    head: str = "valves"
    stuck_memory: bool = False

    def __post_init__(self) -> None:
        if self.window < 1 or not self.hidden or min(self.hidden) < 1:
            raise ValueError(f"StudentConfig: window >= 1 and hidden widths >= 1 needed, got "
                             f"window={self.window}, hidden={self.hidden}")
        if self.head not in HEADS:
            raise ValueError(f"StudentConfig: head must be one of {sorted(HEADS)}, "
                             f"got {self.head!r}")

    @property
    def inputs(self) -> int:
        return STEP_FEATURES * self.window + (STUCK_FEATURES if self.stuck_memory else 0)

    @property
    def outputs(self) -> int:
        return HEADS[self.head]

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["hidden"] = list(self.hidden)
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "StudentConfig":
        return cls(window=int(d["window"]), hidden=tuple(int(h) for h in d["hidden"]),
                   head=str(d.get("head", "valves")),
                   stuck_memory=bool(d.get("stuck_memory", False)))


@dataclass(frozen=True)
class TrainingConfig:
    """Everything the checkpoint depends on, with the distribution file and the code.

    iterations: DAgger iterations; envs: plants per iteration; life_intervals:
    intervals each plant runs (<= the distribution's life); label_fraction:
    fraction of the student's states the teacher labels; dagger: False trains
    without DAgger (every iteration driven and labelled by the teacher alone:
    behaviour cloning); epochs, batch, lr: the student's fit after each
    iteration; max_samples: data set size kept; window, hidden, head: the
    student (:class:`StudentConfig`); inputs: how its first layer is
    parametrized while it trains ("window": on the scaled window; "rates": on
    the newest levels and valves and the first differences of the levels
    between steps, each standardized by the first iteration's data; the
    checkpoint folds this linear map into the first layer, so the flown
    network reads the window either way); regret: with the joint head, the
    weight of the expected regret (the teacher's summed-reward loss of the
    student's choice, per unit of the data's mean regret) added to the cross
    entropy (the valves head has none); hold, horizon: the teacher's planner
    (oracle-mpc's H and L); extra_holds: more hold lengths the teacher's
    plans try, each setting valued by the best of its plans (() for hold
    alone); second_stage: how many of the best settings the teacher also
    values by their two-stage plans (held ``hold`` steps, then any setting to
    the horizon), 0 for none; recheck: how many of the best settings the
    teacher values again over recheck_horizon steps (their plans held each
    hold length, then continued as recheck_rule says; the label the best of
    them), 0 for none; recheck_rule: what a rechecked plan does after its
    hold, "closed" (every valve), "balance" (the balance rule in closed loop)
    or "best" (the better of the two, with all closed always rechecked too);
    seed: draws,
    pool plants, initial weights and minibatches; members: students trained one after another with seeds seed,
    seed + 1, ... (each its own plants, labels and weights) and flown as one
    network whose logits are their mean (:func:`ensemble`); privileged: weight
    of the privileged head's loss (a second head on the last hidden layer that
    learns which valves are stuck, in training only: see
    ftc.experiments.adaptive.dagger), 0 for none; privileged_params: weight of
    the parameter head's loss (another head, in training only, that regresses
    the true degraded parameters in force: the pumps' capacity, the tanks'
    conductance and the engines' demand), 0 for none; stuck_memory: the student
    also reads which valves it has seen stuck (:class:`HistoryWindow`);
    teacher_stuck: which stuck valves the teacher plans with, "all" (every
    one, from its event on) or "seen" (those in the student's stuck memory
    at that step, the others as healthy: what the student can know);
    explore, explore_hold: in the student-driven plants, the chance per step
    that a perturbation begins, a random valve setting held for 1 to
    explore_hold steps in place of the student's (the teacher labels those
    states as any other: noise injection, so that the data hold states off
    both the student's and the teacher's paths and the way back from them),
    0 for none."""

    iterations: int = 8
    envs: int = 48
    life_intervals: int = 10
    label_fraction: float = 0.4
    dagger: bool = True
    epochs: int = 4
    batch: int = 512
    lr: float = 1e-3
    max_samples: int = 600_000
    window: int = 12
    hidden: tuple[int, ...] = (128, 128)
    head: str = "joint"
    inputs: str = "window"
    regret: float = 5.0
    hold: int = 2
    horizon: int = 6
    extra_holds: tuple[int, ...] = (1, 3, 6)
    second_stage: int = 0
    recheck: int = 4
    recheck_horizon: int = 30
    recheck_rule: str = "best"
    seed: int = 0
    members: int = 4
    privileged: float = 0.0
    privileged_params: float = 0.0
    stuck_memory: bool = True
    teacher_stuck: str = "seen"
    explore: float = 0.004
    explore_hold: int = 64

    def __post_init__(self) -> None:
        if self.inputs not in INPUTS:
            raise ValueError(f"TrainingConfig: inputs must be one of {list(INPUTS)}, "
                             f"got {self.inputs!r}")
        if not self.regret >= 0:
            raise ValueError(f"TrainingConfig: regret must be >= 0, got {self.regret}")
        for name in ("privileged", "privileged_params"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"TrainingConfig: {name} must be >= 0, "
                                 f"got {getattr(self, name)}")
        for name in ("second_stage", "recheck"):  # settings: 0 to all of them
            if not 0 <= getattr(self, name) <= 2 ** NUM_TANKS:
                raise ValueError(f"TrainingConfig: {name} must be in [0, {2 ** NUM_TANKS}], "
                                 f"got {getattr(self, name)}")
        if self.recheck_horizon < 1:
            raise ValueError(f"TrainingConfig: recheck_horizon must be >= 1, "
                             f"got {self.recheck_horizon}")
        if self.recheck and self.recheck_horizon <= self.horizon:
            raise ValueError(f"TrainingConfig: recheck_horizon ({self.recheck_horizon}) must be "
                             f"longer than the horizon ({self.horizon}) with a recheck")
        if self.recheck_rule not in RECHECK_RULES:
            raise ValueError(f"TrainingConfig: recheck_rule must be one of "
                             f"{list(RECHECK_RULES)}, got {self.recheck_rule!r}")
        if self.recheck_rule != "closed" and not self.recheck:
            raise ValueError(f"TrainingConfig: recheck_rule {self.recheck_rule!r} needs a "
                             "recheck (recheck >= 1): without one it would change nothing")
        if min((self.hold, *self.extra_holds)) < 1:
            raise ValueError(f"TrainingConfig: holds must be >= 1 step, "
                             f"got {[self.hold, *self.extra_holds]}")
        if self.members < 1:
            raise ValueError(f"TrainingConfig: members must be >= 1, got {self.members}")
        if not 0.0 <= self.explore <= 1.0 or self.explore_hold < 1:
            raise ValueError(f"TrainingConfig: explore must be in [0, 1] and explore_hold >= 1, "
                             f"got {self.explore} and {self.explore_hold}")
        if self.teacher_stuck not in TEACHER_STUCK:
            raise ValueError(f"TrainingConfig: teacher_stuck must be one of "
                             f"{list(TEACHER_STUCK)}, got {self.teacher_stuck!r}")
        if self.teacher_stuck == "seen" and not self.stuck_memory:
            raise ValueError("TrainingConfig: teacher_stuck 'seen' needs the stuck memory "
                             "(the valves seen stuck are the student's)")
        if self.stuck_memory and self.inputs != "window":
            raise ValueError("TrainingConfig: the stuck memory needs inputs 'window', got "
                             f"{self.inputs!r}")

    def student(self) -> StudentConfig:
        return StudentConfig(window=self.window, hidden=tuple(self.hidden), head=self.head,
                             stuck_memory=self.stuck_memory)

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        d["hidden"] = list(self.hidden)
        return d


class HistoryWindow:
    """N windows of history, newest first: ``features()`` is (N, 12 W) float32,
    followed with the stuck memory by 12 more.

    Slot k holds the levels published k steps ago and the valves commanded on
    the step that led to them (closed for an episode's first levels), so the
    newest slot pairs the current levels with the last command.
    ``start(levels, which)``: envs ``which`` (bool (N,), default all) begin an
    episode at ``levels`` (N, 6); ``push(levels, valves, started, applied)``:
    after a step with ``valves`` (N, 6) commanded the plant published
    ``levels`` (N, 6) and the valves it ``applied`` (N, 6); rows where
    ``started`` is set began a new episode with these levels (their window is
    refilled). Levels are clipped to [0, 1] as the observation space is.

    The stuck memory (``stuck_memory``, ``stuck`` (N, 12) of 0/1, read as
    2 x - 1 by ``features``): per valve, whether it was last seen stuck
    closed (applied closed when commanded open) or stuck open (applied open
    when commanded closed), closed for valves 1-6 then open for valves 1-6. A valve stuck as it is commanded cannot be told from a healthy
    one, so it is seen at the first command against its state. ``push`` with
    ``applied`` or ``see(commanded, applied)`` (a controller's transitions:
    the command in force and the valves the plant published) feed it; from a
    pool, take ``applied`` with same-step autoreset (with next-step autoreset
    the reset step ignores its command and applies none). The memory outlives episodes (a plant's valves stay stuck); ``forget(which)``
    clears it for envs that are new plants."""

    def __init__(self, num_envs: int, window: int, stuck_memory: bool = False) -> None:
        self.window = window
        self._buf = np.zeros((num_envs, window, STEP_FEATURES), np.float32)
        self.memory = StuckMemory(num_envs) if stuck_memory else None

    @property
    def stuck(self) -> np.ndarray | None:
        """The stuck memory (N, 12) of 0/1 (:class:`ftc.learning.stuck.StuckMemory`), or None."""
        return None if self.memory is None else self.memory.stuck

    def start(self, levels: np.ndarray, which: np.ndarray | None = None) -> None:
        rows = np.arange(len(self._buf)) if which is None else np.flatnonzero(which)
        if not len(rows):
            return
        scaled = 2.0 * np.clip(np.asarray(levels, np.float32)[rows], 0.0, 1.0) - 1.0
        self._buf[rows, :, :NUM_TANKS] = scaled[:, None, :]
        self._buf[rows, :, NUM_TANKS:] = -1.0  # closed

    def forget(self, which: np.ndarray | None = None) -> None:
        """Clear the stuck memory of envs ``which`` (bool (N,), default all)."""
        if self.memory is not None:
            self.memory.forget(which)

    def push(self, levels: np.ndarray, valves: np.ndarray,
             started: np.ndarray | None = None, applied: np.ndarray | None = None) -> None:
        self._buf[:, 1:] = self._buf[:, :-1]
        self._buf[:, 0, :NUM_TANKS] = 2.0 * np.clip(np.asarray(levels, np.float32), 0.0,
                                                    1.0) - 1.0
        self._buf[:, 0, NUM_TANKS:] = 2.0 * np.asarray(valves, np.float32) - 1.0
        if applied is not None:
            self.see(valves, applied)
        if started is not None and np.any(started):
            self.start(levels, started)

    def see(self, commanded: np.ndarray, applied: np.ndarray) -> None:
        """The plant applied ``applied`` (N, 6) on a step ``commanded`` (N, 6):
        a valve applied otherwise enters the stuck memory (if kept)."""
        if self.memory is not None:
            self.memory.see(commanded, applied)

    def features(self) -> np.ndarray:
        x = self._buf.reshape(len(self._buf), -1)
        if self.memory is None:
            return x.copy()
        return np.concatenate([x, self.memory.features()], axis=1)


class HistoryPolicy(nn.Module):
    """features (N, 12 W) -> logits (six, or 64 with the joint head); ``act``
    maps them to valves (:class:`StudentConfig`).

    While it trains, a fixed affine map of the input (``set_input_map``: the
    rates parametrization) may precede the first layer; :meth:`record` folds it
    into that layer, so a checkpoint is always a plain MLP on the window."""

    def __init__(self, config: StudentConfig = StudentConfig()) -> None:
        super().__init__()
        self.config = config
        widths = (config.inputs, *config.hidden)
        layers: list[nn.Module] = []
        for a, b in zip(widths[:-1], widths[1:]):
            layers += [nn.Linear(a, b), nn.Tanh()]
        layers.append(nn.Linear(widths[-1], config.outputs))
        self.net = nn.Sequential(*layers)
        self.input_map: torch.Tensor | None = None  # (F, F): x -> x @ map.T - shift
        self.input_shift: torch.Tensor | None = None

    def set_input_map(self, matrix: np.ndarray, shift: np.ndarray) -> None:
        self.input_map = torch.as_tensor(np.asarray(matrix, np.float32))
        self.input_shift = torch.as_tensor(np.asarray(shift, np.float32))

    def trunk(self, features: torch.Tensor) -> torch.Tensor:
        """The last hidden layer's activations (what the output layer reads)."""
        if self.input_map is not None:
            features = features @ self.input_map.T - self.input_shift
        return self.net[:-1](features)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.net[-1](self.trunk(features))

    @torch.no_grad()
    def act(self, features: np.ndarray) -> np.ndarray:
        """Valves (N, 6) int8 for features (N, 12 W)."""
        logits = self.forward(torch.as_tensor(features, dtype=torch.float32))
        if self.config.head == "joint":
            setting = logits.argmax(dim=1).numpy()
            return ((setting[:, None] >> np.arange(NUM_TANKS)) & 1).astype(np.int8)
        return (logits > 0).numpy().astype(np.int8)

    def record(self) -> dict[str, Any]:
        """Its architecture and weights (loadable with torch.load(weights_only=True)),
        the input map folded into the first layer."""
        state = {k: v.detach().clone() for k, v in self.state_dict().items()}
        if self.input_map is not None:
            w = state["net.0.weight"].double()
            state["net.0.weight"] = (w @ self.input_map.double()).float()
            state["net.0.bias"] = (state["net.0.bias"].double()
                                   - w @ self.input_shift.double()).float()
        return {"config": self.config.to_json(), "state": state}

    @classmethod
    def from_record(cls, record: dict[str, Any]) -> "HistoryPolicy":
        policy = cls(StudentConfig.from_json(record["config"]))
        policy.load_state_dict(record["state"])
        policy.eval()
        return policy


def ensemble(policies: list[HistoryPolicy]) -> HistoryPolicy:
    """One plain MLP whose logits are the mean of ``policies``' logits (same
    window, head and depth): the members side by side in each hidden layer
    (the first layer's rows stacked, the deeper layers block-diagonal) and the
    last layer's weights each divided by their count. It acts as the members'
    vote would, in one forward pass, so the node flies it as any student."""
    first = policies[0].config
    if any(p.config.window != first.window or p.config.head != first.head or
           p.config.stuck_memory != first.stuck_memory or
           len(p.config.hidden) != len(first.hidden) for p in policies):
        raise ValueError("ensemble: the members differ in window, head, stuck memory or depth: "
                         f"{[p.config for p in policies]}")
    widths = tuple(sum(p.config.hidden[j] for p in policies) for j in range(len(first.hidden)))
    merged = HistoryPolicy(StudentConfig(window=first.window, hidden=widths, head=first.head,
                                         stuck_memory=first.stuck_memory))
    records = [p.record()["state"] for p in policies]  # input maps folded in
    layers = len(first.hidden) + 1
    with torch.no_grad():
        for j in range(layers):
            weight = merged.net[2 * j].weight
            bias = merged.net[2 * j].bias
            weight.zero_()
            bias.zero_()
            row = col = 0
            for state in records:
                w, b = state[f"net.{2 * j}.weight"], state[f"net.{2 * j}.bias"]
                if j == layers - 1:  # the head: the mean of the members' logits
                    weight[:, col:col + w.shape[1]] = w / len(records)
                    bias += b / len(records)
                else:
                    cols = slice(0, w.shape[1]) if j == 0 else slice(col, col + w.shape[1])
                    weight[row:row + w.shape[0], cols] = w
                    bias[row:row + w.shape[0]] = b
                row += w.shape[0]
                col += w.shape[1] if j > 0 else 0
    merged.eval()
    return merged


def rates_map(window: int, features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rates parametrization for a window of ``window`` steps: (matrix (F, F),
    shift (F,)) such that ``x @ matrix.T - shift`` holds the newest levels
    (slot 0), in slot k >= 1 the levels' change over that step (slot k-1 minus
    slot k), and every valve unchanged, each standardized to zero mean and unit
    deviation over ``features`` (N, F) (a deviation under 1e-6 is taken as 1)."""
    f = STEP_FEATURES * window
    d = np.eye(f)
    for k in range(1, window):
        for i in range(NUM_TANKS):
            d[k * STEP_FEATURES + i, (k - 1) * STEP_FEATURES + i] = 1.0
            d[k * STEP_FEATURES + i, k * STEP_FEATURES + i] = -1.0
    z = np.asarray(features, np.float64) @ d.T
    mean, std = z.mean(axis=0), z.std(axis=0)
    std = np.where(std > 1e-6, std, 1.0)
    return d / std[:, None], mean / std


def code_digest() -> str:
    """The code a checkpoint depends on: the trainer's import closure and the
    C++ sources of the physics core it simulates with (:mod:`ftc.common.source_key`)."""
    return hashlib.sha256((closure_digest([TRAINER]) + (native_source_digest() or "")).encode()
                          ).hexdigest()


def checkpoint_file(cache_dir: str, config: TrainingConfig, distribution_text: str) -> Path:
    """Where the checkpoint trained with ``config`` on the distribution declared
    by ``distribution_text``, by this code, is cached under ``cache_dir``."""
    fields_ = {"config": config.to_json(), "distribution": distribution_text,
               "code": code_digest(), "version": CACHE_VERSION}
    key = hashlib.sha256(json.dumps(fields_, sort_keys=True).encode()).hexdigest()[:16]
    return Path(os.path.expanduser(cache_dir)) / f"adaptive-{key}.pt"
