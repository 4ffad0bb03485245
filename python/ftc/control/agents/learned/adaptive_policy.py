"""adaptive-policy: the student trained in simulation over many degradations
(docs/adaptive.md), flown as it is: one forward pass per step on the recent
history of levels and valves, no plant equations and no fault detection at
run time; by default nothing learned on the plant. With ``--fine-tune`` it
keeps adapting between intervals (or on a worker thread, on a real-time
plant): expert iteration on a model learned from the plant's own steps
(:mod:`ftc.control.agents.learned.online_tune`); the acting is unchanged.

The checkpoint is built once by ``python -m ftc.experiments.adaptive train``
and cached under a key of its training config, the training distribution's
file and the code (:func:`ftc.learning.history_policy.checkpoint_file`);
this agent loads it (``--checkpoint`` names another file) and refuses to run
without one (exit 2, the command to build it named), so a benchmark never
trains it. It imports neither the training nor its teacher (the import
contract "learned-no-equations" in pyproject.toml).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, ClassVar

import numpy as np

from ftc.common.cli import at_least, between, positive
from ftc.common.errors import CheckpointError, UsageError
from ftc.common.paths import SCENARIO_DIR
from ftc.control.agents.learned.online_tune import FineTuneSettings, OnlineTeacher
from ftc.control.run.agent import Agent, StepContext, Transition
from ftc.control.run.background import OneJob
from ftc.control.run.config import RunConfig
from ftc.learning.history_policy import HistoryPolicy, HistoryWindow, TrainingConfig, \
    checkpoint_file
from ftc.plant.link import PlantObservation

TRAIN_COMMAND = ".venv/bin/python -m ftc.experiments.adaptive train"
FINE_TUNE_COLUMNS = ("fine_tune_states", "fine_tune_corrected", "fine_tune_loss",
                     "fine_tune_seconds", "model_one_step_rmse", "stuck_valves", "stuck_detected")


@dataclass
class AdaptiveConfig(RunConfig):
    """A run of the adaptive student: which checkpoint it flies, and whether it
    keeps adapting on the plant (the fine-tune's options act only with it)."""

    NEEDS: ClassVar[dict[str, Any]] = {name: ("fine_tune", True) for name in (
        "fine_tune_margin", "fine_tune_candidates", "fine_tune_lr", "fine_tune_epochs",
        "fine_tune_memory")}

    method: str = field(default="adaptive-policy", metadata={"help": "the method"})
    checkpoint: str = field(default="", metadata={"help": (
        "the student's checkpoint file ('': the one `python -m ftc.experiments.adaptive "
        "train` cached for its default training options)")})
    adaptive_cache: str = field(default="~/.cache/ftc/adaptive", metadata={
        "run_local": True, "help": "directory of the cached checkpoints"})
    fine_tune: bool = field(default=False, metadata={"help": (
        "after each interval, fine-tune the student toward the settings a model learned "
        "from the plant's steps (learned-mpc's) rates better than its own choice by "
        "--fine-tune-margin; off the control loop (docs/adaptive.md)")})
    fine_tune_margin: float = field(default=0.5, metadata={"check": between(0.0, 100.0), "help": (
        "fine-tune: summed reward over the 10-step horizon by which the learned model's "
        "best setting must beat the student's choice to become its label")})
    fine_tune_candidates: int = field(default=2, metadata={"check": at_least(1, 64), "help": (
        "fine-tune: how many settings may become labels, the student's most probable ones "
        "(its choice and the next; 64: every setting)")})
    fine_tune_lr: float = field(default=1e-4, metadata={"check": positive(1.0), "help": (
        "fine-tune: Adam's learning rate")})
    fine_tune_epochs: int = field(default=4, metadata={"check": at_least(1, 1000), "help": (
        "fine-tune: passes over the labelled memory after each interval")})
    fine_tune_memory: int = field(default=2048, metadata={"check": at_least(1, 1_000_000), "help": (
        "fine-tune: labelled states kept (the newest; those not corrected keep the "
        "student's own choice, so it does not forget them)")})

    def validate(self) -> None:
        super().validate()
        if self.checkpoint and not Path(self.checkpoint).is_file():
            raise ValueError(f"--checkpoint {self.checkpoint}: no such file (build one with "
                             f"`{TRAIN_COMMAND}`)")
        if not self.adaptive_cache.strip():
            raise ValueError("--adaptive-cache must name a directory, got ''")


def default_checkpoint(cache_dir: str) -> Path:
    """The cached checkpoint of the default training options, distribution and code."""
    text = (SCENARIO_DIR / "training" / "adaptive.toml").read_text()
    return checkpoint_file(cache_dir, TrainingConfig(), text)


class AdaptivePolicyAgent(Agent):
    """Acts with the student on its window of (levels, last valves); learns nothing."""

    name = "adaptive-policy"
    Config = AdaptiveConfig
    extra_columns = FINE_TUNE_COLUMNS  # empty without --fine-tune

    def __init__(self, cfg: AdaptiveConfig) -> None:
        self.cfg = cfg
        self.path = Path(cfg.checkpoint) if cfg.checkpoint else default_checkpoint(
            cfg.adaptive_cache)
        self.policy: HistoryPolicy | None = None
        self.window: HistoryWindow | None = None
        self._last: np.ndarray | None = None
        self.teacher = OnlineTeacher(FineTuneSettings(
            margin=cfg.fine_tune_margin, candidates=cfg.fine_tune_candidates,
            lr=cfg.fine_tune_lr, epochs=cfg.fine_tune_epochs, memory=cfg.fine_tune_memory,
            seed=cfg.seed)) if cfg.fine_tune else None
        self._jobs = OneJob("adaptive-fine-tune")
        self._late: list[tuple[int, dict[str, Any]]] = []
        self.on_learned: Callable[[int], None] | None = None

    @classmethod
    def from_configs(cls, configs: dict[str, Any]) -> "AdaptivePolicyAgent":
        return cls(configs["controller"])

    def _load(self) -> HistoryPolicy:
        if self.policy is None:
            import torch

            torch.set_num_threads(1)
            if not self.path.is_file():
                raise UsageError(f"adaptive-policy: no checkpoint at {self.path}; build it "
                                 f"with `{TRAIN_COMMAND}`")
            try:
                record = torch.load(self.path, weights_only=True)
                self.policy = HistoryPolicy.from_record(record["policy"])
            except (OSError, RuntimeError, KeyError, TypeError, ValueError) as e:
                raise UsageError(f"adaptive-policy: {self.path} is not a student checkpoint "
                                 f"({type(e).__name__}: {e})") from None
            self.window = HistoryWindow(1, self.policy.config.window,
                                        self.policy.config.stuck_memory)
        return self.policy

    def prepare(self) -> dict[str, Any]:
        self._load()
        return self.teacher.prepare() if self.teacher is not None else {}

    def start_episode(self, obs: PlantObservation) -> None:
        self._load()
        self.window.start(obs.level[None, :])
        self._last = None

    def act(self, obs: PlantObservation, ctx: StepContext) -> np.ndarray:
        self._load()
        if self._last is not None:  # the levels this step's command acts on
            self.window.push(obs.level[None, :], self._last[None, :])
            if ctx.evaluation:  # no Transition comes: the memory from the answer itself
                self.window.see(self._last[None, :], obs.valves[None, :])
        self._poll()
        features = self.window.features()
        u = self.policy.act(features)[0]
        self._last = u
        if self.teacher is not None and not ctx.evaluation:
            self.teacher.record(features[0], obs.level, u)
        return u

    # -- the fine-tune (--fine-tune) ---------------------------------------------------
    def observe(self, t: Transition) -> None:
        # the stuck memory: the command in force against the valves the plant applied
        # (a real-time step on an older command compares with that one)
        self._load()
        self.window.see(t.valves[None, :], t.next_obs.valves[None, :])
        if self.teacher is not None:
            self.teacher.observe(t)

    def end_interval(self, interval: int, data: Any) -> dict[str, Any]:
        if self.teacher is None:
            return {}
        self._poll(wait=True)  # one job at a time
        job = self.teacher.job(self._load())
        if not self.background_learning:  # between intervals
            self.policy, metrics = job()
            return metrics
        self._jobs.submit(job, interval)
        return {}

    @property
    def learning(self) -> bool:  # type: ignore[override]
        return self._jobs.running

    def _poll(self, wait: bool = False) -> None:
        """Swap in the student a finished job tuned (between two steps)."""
        done = self._jobs.take(wait)  # a job's error is raised here, in the loop
        if done is None:
            return
        (self.policy, metrics), interval = done
        self._late.append((interval, metrics))
        if self.on_learned is not None:
            self.on_learned(interval)

    def late_metrics(self) -> list[tuple[int, dict[str, Any]]]:
        self._poll()
        late, self._late = self._late, []
        return late

    def finish(self) -> None:
        self._poll(wait=True)

    def close(self) -> None:
        self._jobs.close()

    def state_dict(self) -> dict[str, Any]:
        self._load()
        memory = {} if self.window.stuck is None else {"stuck_memory": self.window.stuck.tolist()}
        if self.teacher is None:
            return memory
        if self._jobs.running:  # the runner saves from on_learned instead
            raise RuntimeError("the agent's state is changing: a fine-tune is running")
        return {"student": self._load().record(), "fine_tune": self.teacher.state_dict(),
                **memory}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self._load()
        if self.window.stuck is not None:  # the valves seen stuck before the resume
            if "stuck_memory" not in state:
                raise CheckpointError("checkpoint lacks the student's stuck memory")
            memory = np.asarray(state["stuck_memory"], np.float32)
            if memory.shape != self.window.stuck.shape:
                raise CheckpointError(f"checkpoint's stuck memory has shape {memory.shape}, "
                                      f"not {self.window.stuck.shape}")
            self.window.stuck[:] = memory
        if self.teacher is None:
            return
        if not {"student", "fine_tune"} <= set(state):
            raise CheckpointError("checkpoint lacks the fine-tuned student")
        self._load()
        self.policy = HistoryPolicy.from_record(state["student"])
        self.teacher.load_state_dict(state["fine_tune"])

    def config_doc(self) -> dict[str, Any]:
        return {"adaptive_checkpoint": str(self.path), "adaptive_fine_tune": self.cfg.fine_tune}
