"""The options every MPC method has (``python -m ftc.mpc``): the receding
horizon, the planner and its settings. Each method adds its own in its agent's
module (:class:`ftc.control.agents.physics.mpc.OracleConfig`, ...)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

from ftc.common.cli import at_least, between
from ftc.control.run.config import MAX_STEPS_PER_INTERVAL, RunConfig

PLANNERS = ("hold", "cem", "two-stage")


@dataclass
class MPCConfig(RunConfig):
    """What every MPC run depends on: the run's and the planner's options."""

    NEEDS: ClassVar[dict[str, tuple[str, Any]]] = {
        "cem_samples": ("planner", "cem"), "cem_iterations": ("planner", "cem"),
        "cem_elites": ("planner", "cem"), "cem_smoothing": ("planner", "cem"),
        "two_stage_hold": ("planner", "two-stage"), "two_stage_keep": ("planner", "two-stage")}

    method: str = field(default="oracle-mpc", metadata={"help": "the method (--help lists them)"})
    scenario: str | None = field(default="single", metadata={"help": (
        "fault scenario given to the plant and read by the oracle: a packaged one's name "
        "(single, multiple, nominal, abrupt) or a TOML file ('' = nominal)")})
    seed: int = field(default=0, metadata={"check": at_least(0, 2**31 - 1), "help": (
        "seeds the plant, the world model and the cross-entropy search")})
    out: str = field(default="runs/mpc", metadata={"help": "output directory"})
    steps_per_interval: int = field(default=512, metadata={
        "check": at_least(1, MAX_STEPS_PER_INTERVAL),
        "help": "real steps per interval; forwarded to the plant (paper: 512)"})
    planner: str = field(default="hold", metadata={"choices": PLANNERS, "help": (
        "hold: the 64 settings each held --hold steps then all closed; cem: "
        "cross-entropy search over per-step valve probabilities; two-stage: each setting "
        "held --two-stage-hold steps then each setting to the horizon (4,096 plans), and "
        "the hold plans")})
    horizon: int = field(default=10, metadata={"check": at_least(1, 10_000), "help": "L: planning horizon, steps"})
    hold: int = field(default=3, metadata={"check": at_least(1, 10_000), "help": (
        "H: steps each candidate setting is held before all valves close (hold planner; "
        "measured: H=3 beat 1, 5 and 10 in an independent simulation)")})
    truncate_at_interval: bool = field(default=True, metadata={"help": (
        "plan no further than the interval's last step (the plant cuts the episode there "
        "and the next interval starts from full tanks)")})
    cem_samples: int = field(default=64, metadata={"check": at_least(1, 1_000_000), "help": "cem: sequences sampled per iteration"})
    cem_iterations: int = field(default=4, metadata={"check": at_least(1, 10_000), "help": "cem: iterations per decision"})
    cem_elites: int = field(default=8, metadata={"check": at_least(1, 1_000_000), "help": "cem: best sequences refitted to"})
    cem_smoothing: float = field(default=0.2, metadata={"check": between(0.0, 1.0), "help": (
        "cem: weight of the old probabilities in each update (0: elites only)")})
    two_stage_hold: int = field(default=2, metadata={"check": at_least(1, 10_000), "help": (
        "two-stage: H1, steps the first setting is held before the second")})
    two_stage_keep: int = field(default=64, metadata={"check": at_least(1, 64), "help": (
        "two-stage: first settings expanded into their 64 second stages, the best by their "
        "hold plans' summed reward (64: all, 4,096 plans)")})
    evaluate: bool = field(default=True, metadata={"help": (
        "after each interval run one evaluation episode (age frozen) with the planner "
        "(eval_reward_per_step; MPC is deterministic, so it measures the same policy)")})

    def validate(self) -> None:
        super().validate()
        if self.hold > self.horizon:
            raise ValueError(f"--hold ({self.hold}) must not exceed --horizon ({self.horizon})")
        if self.planner == "two-stage" and self.two_stage_hold > self.horizon:
            raise ValueError(f"--two-stage-hold ({self.two_stage_hold}) must not exceed "
                             f"--horizon ({self.horizon})")
        if self.cem_elites > self.cem_samples:
            raise ValueError(f"--cem-elites ({self.cem_elites}) must not exceed --cem-samples "
                             f"({self.cem_samples})")
