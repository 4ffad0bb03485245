"""The options of an MPC run (``python -m ftc.mpc``): one dataclass for every
method of that tool, each option's help saying which methods read it (the
command line refuses the others: :meth:`MPCConfig.ignored`). Its own module so
that a controller can take its options without importing the others' code."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from ftc.common.cli import at_least, between, positive
from ftc.control import registry
from ftc.control.config import MAX_INTERVALS, MAX_STEPS_PER_INTERVAL, RunConfig

METHODS = registry.config_values("ftc.mpc")  # the values of MPCConfig.method
PLANNERS = ("hold", "cem", "two-stage", "episode")


@dataclass
class MPCConfig(RunConfig):
    """Everything an MPC run depends on."""

    method: str = field(default="oracle-mpc", metadata={"choices": METHODS, "help": (
        "oracle-mpc: plans on the true degraded physics (knows the faults); model-mpc: plans "
        "on the learned world model, refitted every interval (never told the faults); "
        "identified-mpc: plans on the plant's physics with its parameters identified from the "
        "observed data (assumes the plant's structure, never told the faults); learned-mpc: "
        "plans on a model learned from the observed steps alone, updated after every step "
        "(no plant equations, never told the faults)")})
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
        "the hold plans; episode (oracle-mpc only): whole episodes optimised on the true "
        "physics and played, never below the hold planner's closed loop "
        "(ftc.control.episode_planner)")})
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
    episode_sweeps: int = field(default=6, metadata={"check": at_least(1, 1000), "help": (
        "episode: coordinate-ascent sweeps over an episode's steps at most (each tries every "
        "setting held 1, 2, 4 and 8 steps at every step)")})
    episode_tolerance: float = field(default=1e-6, metadata={"check": positive(1.0), "help": (
        "episode: the plan is remade where an observed level differs from its prediction "
        "by more than this (plus 6 times the scenario's sensor-noise std), m")})
    rollout_closed_form: bool = field(default=False, metadata={"help": (
        "oracle-mpc, identified-mpc: step the rollouts with two or more valves open in closed "
        "form (_core.BatchRollout's exact_active_conduit; CVODE only where a tank is pinned): "
        "within CVODE's tolerances of it and several times faster")})
    rollout_rtol: float = field(default=1e-6, metadata={"check": positive(1.0), "help": (
        "oracle-mpc, identified-mpc: CVODE relative tolerance of the rollouts (measured: 1e-6 moves summed "
        "10-step rewards by < 2e-5 against 1e-12, never the chosen action in the bench, "
        "and is 1.6x faster than the plant's 1e-8)")})
    rollout_atol: float = field(default=1e-8, metadata={"check": positive(1.0), "help": "oracle-mpc, identified-mpc: CVODE absolute tolerance, m"})
    model_window: int = field(default=1, metadata={"check": at_least(1, MAX_INTERVALS), "help": (
        "model-mpc: intervals of real data each refit trains on (1 = the interval just run, "
        "as the controller's default)")})
    model_engine: str = field(default="numpy", metadata={"choices": ("numpy", "torch"), "help": (
        "model-mpc: how the world model is trained: numpy (several times faster at this size) or "
        "torch (autograd); the same algorithm, minibatches and stopping rule, float32 "
        "rounding differs (docs/benchmarks.md)")})
    model_episodes: int = field(default=50, metadata={"check": at_least(1, 100_000), "help": (
        "model-mpc: nominal random-valve episodes for world-model pretraining (paper: 50)")})
    pretrain_cache: str = field(default="~/.cache/ftc/pretrain", metadata={
        "run_local": True, "help": (
        "model-mpc: directory of pretrained world models keyed by a hash of everything "
        "pretraining depends on (episodes, seed, model config, code); a hit skips the "
        "pretraining with the same weights ('' disables)")})
    identify_every: int = field(default=64, metadata={"check": at_least(0, 1_000_000), "help": (
        "identified-mpc: re-identify the parameters every N steps of an interval from its data "
        "so far (0: only at interval ends)")})
    identify_trigger: float = field(default=1e-4, metadata={"check": between(0.0, 1.0), "help": (
        "identified-mpc: a one-step prediction error above this (m) means the plant changed: the "
        "parameters are re-identified from the data since then at once, not at the next "
        "scheduled refit (0: off, relearn on the schedule only)")})
    learn_features: int = field(default=256, metadata={"check": at_least(1, 100_000), "help": (
        "learned-mpc: random ReLU features of the learned model (beside a constant, the "
        "12 inputs and their 66 pairwise products)")})
    learn_forget: float = field(default=0.998, metadata={"check": between(0.5, 1.0), "help": (
        "learned-mpc: weight a step keeps per later step in the model's fit (0.998: a "
        "half-life of 350 steps; 1: never forget)")})
    learn_ridge: float = field(default=0.01, metadata={"check": positive(1e6), "help": (
        "learned-mpc: weight of the prior (the fit at the last interval's end) against the "
        "data, per feature direction")})
    learn_episodes: int = field(default=100, metadata={"check": at_least(1, 100_000), "help": (
        "learned-mpc: nominal episodes the model is first fitted on: half the paper's "
        "random valves held up to 30 steps, half sparse openings (each valve open with a "
        "probability drawn from [0, 0.3], held up to 10 steps), where closed valves, the "
        "best policy's usual choice, are common")})
    learn_terminal_band: float = field(default=0.005, metadata={"check": between(0.0, 1.0), "help": (
        "learned-mpc: a predicted step ends the episode only if it leaves this much less "
        "fuel (m^3) than the demand estimated from what was burnt; a model slightly wrong "
        "near the end otherwise plans on a reset that never comes (fuel stranded behind a "
        "dead pump: docs/controller.md)")})
    evaluate: bool = field(default=True, metadata={"help": (
        "after each interval run one evaluation episode (age frozen) with the planner "
        "(eval_reward_per_step; MPC is deterministic, so it measures the same policy)")})

    def ignored(self) -> dict[str, str]:
        """The options that have no effect on this run, each with why (the
        command line refuses them when given)."""
        out = {}
        for f in dataclasses.fields(self):
            if f.name.startswith("cem_") and self.planner != "cem":
                out[f.name] = f"with --planner {self.planner}"
            elif (f.name.startswith("model_") or f.name == "pretrain_cache") and \
                    self.method != "model-mpc":
                out[f.name] = f"with --method {self.method} (it configures model-mpc)"
            elif f.name.startswith("two_stage_") and self.planner != "two-stage":
                out[f.name] = f"with --planner {self.planner}"
            elif f.name.startswith("episode_") and self.planner != "episode":
                out[f.name] = f"with --planner {self.planner}"
            elif f.name.startswith("identify_") and self.method != "identified-mpc":
                out[f.name] = f"with --method {self.method} (it configures identified-mpc)"
            elif f.name.startswith("rollout_") and self.method in ("model-mpc", "learned-mpc"):
                out[f.name] = f"with --method {self.method} (it plans on a learned model)"
            elif f.name.startswith("learn_") and self.method != "learned-mpc":
                out[f.name] = f"with --method {self.method} (it configures learned-mpc)"
        return out

    def validate(self) -> None:
        super().validate()
        if self.hold > self.horizon:
            raise ValueError(f"--hold ({self.hold}) must not exceed --horizon ({self.horizon})")
        if self.planner == "two-stage" and self.two_stage_hold > self.horizon:
            raise ValueError(f"--two-stage-hold ({self.two_stage_hold}) must not exceed "
                             f"--horizon ({self.horizon})")
        if self.planner == "episode" and self.method != "oracle-mpc":
            raise ValueError(f"--planner episode plans on the true physics: it needs --method "
                             f"oracle-mpc, not {self.method}")
        if self.cem_elites > self.cem_samples:
            raise ValueError(f"--cem-elites ({self.cem_elites}) must not exceed --cem-samples "
                             f"({self.cem_samples})")
