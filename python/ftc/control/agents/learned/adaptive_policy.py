"""adaptive-policy: the student trained in simulation over many degradations
(docs/adaptive.md), flown as it is: one forward pass per step on the recent
history of levels and valves, no plant equations and no fault detection at
run time, nothing learned on the plant.

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
from typing import Any

import numpy as np

from ftc.common.errors import UsageError
from ftc.common.paths import SCENARIO_DIR
from ftc.control.run.agent import Agent, StepContext
from ftc.control.run.config import RunConfig
from ftc.learning.history_policy import HistoryPolicy, HistoryWindow, TrainingConfig, \
    checkpoint_file
from ftc.plant.link import PlantObservation

TRAIN_COMMAND = ".venv/bin/python -m ftc.experiments.adaptive train"


@dataclass
class AdaptiveConfig(RunConfig):
    """A run of the adaptive student: which checkpoint it flies."""

    method: str = field(default="adaptive-policy", metadata={"help": "the method"})
    checkpoint: str = field(default="", metadata={"help": (
        "the student's checkpoint file ('': the one `python -m ftc.experiments.adaptive "
        "train` cached for its default training options)")})
    adaptive_cache: str = field(default="~/.cache/ftc/adaptive", metadata={
        "run_local": True, "help": "directory of the cached checkpoints"})

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

    def __init__(self, cfg: AdaptiveConfig) -> None:
        self.cfg = cfg
        self.path = Path(cfg.checkpoint) if cfg.checkpoint else default_checkpoint(
            cfg.adaptive_cache)
        self.policy: HistoryPolicy | None = None
        self.window: HistoryWindow | None = None
        self._last: np.ndarray | None = None

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
            self.window = HistoryWindow(1, self.policy.config.window)
        return self.policy

    def prepare(self) -> dict[str, Any]:
        self._load()
        return {}

    def start_episode(self, obs: PlantObservation) -> None:
        self._load()
        self.window.start(obs.level[None, :])
        self._last = None

    def act(self, obs: PlantObservation, ctx: StepContext) -> np.ndarray:
        policy = self._load()
        if self._last is not None:  # the levels this step's command acts on
            self.window.push(obs.level[None, :], self._last[None, :])
        u = policy.act(self.window.features())[0]
        self._last = u
        return u

    def config_doc(self) -> dict[str, Any]:
        return {"adaptive_checkpoint": str(self.path)}
