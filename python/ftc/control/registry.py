"""The one list of methods, as data (Gymnasium's ``register(id, entry_point,
kwargs)``): for each controller, the name every tool knows it by
(``ftc.controller --method``, ``ftc.mpc --method``, ``ftc.experiments
--methods``), the agent that runs it, the values of the agent's options that
make this variant, its label and colour, what it is told about the plant, the
settings the experiments recommend, and how they schedule it.

An agent class owns its options: its ``Config`` (a :class:`RunConfig` with
the agent's own fields, each with its help) and its other config ``parts``
(PPO's hyperparameters). The command lines offer exactly those, less the ones
a method fixes (:meth:`Method.offered`), so nothing foreign is offered.

A leaf above the agents: they are named as ``"module:Class"`` and imported
only when a run needs them, so listing the methods imports neither torch nor
the native core, and no agent imports this module. A new controller is its
file plus one :class:`Method` entry (:func:`register`).
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field, fields
from typing import Any, Mapping

from ftc.common.cli import add_dataclass_options, offered
from ftc.control.run.config import ALIASES, canonical  # noqa: F401 - former names, re-exported

# What a method is told about the plant, from least to most.
KNOWS = ("nothing", "a simulator of the plant family, for training only", "the learned model",
         "the plant's equations", "the true faults")
# The tools that run methods, and the name of a run's own config in its config.json.
TOOLS = {"ftc.controller": "controller", "ftc.mpc": "mpc"}


@dataclass(frozen=True, eq=False)
class Method:
    """A controller, as every tool names and runs it.

    name: on every command line and in result paths; agent: the
    ``"module:Class"`` that runs it (its ``Config`` and ``parts`` are the run's
    options, ``from_configs(configs)`` builds it); options: values of the
    agent's options that make this variant (fixed: not offered on its command
    line); label: legend text in figures and tables; color: its colour in
    figures; tool: the module run with ``python -m``; knows: one of
    :data:`KNOWS`; recommended: the options ``ftc.experiments`` adds to its
    runs; cost: relative wall time (scheduling, ETA); learns: a learned policy
    or model (deterministic evaluation, model R^2); benchmark: run by
    ``ftc.experiments benchmark`` by default; compared: offered to
    ``ftc.experiments`` (False: a method whose variants are compared instead);
    cached: its results depend on the scenario only (deterministic planning on
    the true physics), so the benchmark runs it once per scenario and keeps the
    run."""

    name: str
    agent: str
    label: str
    tool: str = "ftc.controller"
    options: Mapping[str, Any] = field(default_factory=dict)
    color: str | None = None
    knows: str = "nothing"
    recommended: tuple[str, ...] = ()
    cost: float = 1.0
    learns: bool = False
    benchmark: bool = True
    compared: bool = True
    cached: bool = False

    def __post_init__(self) -> None:
        if self.knows not in KNOWS:
            raise ValueError(f"method {self.name}: knows {self.knows!r}, not one of {KNOWS}")
        if self.tool not in TOOLS:
            raise ValueError(f"method {self.name}: tool {self.tool!r}, not one of "
                             f"{', '.join(TOOLS)}")

    def agent_class(self) -> type:
        return _load(self.agent)

    def config_class(self) -> type:
        """Its run config: RunConfig and the agent's own options."""
        return self.agent_class().Config

    @property
    def part(self) -> str:
        """The name of its run config in config.json ("controller", "mpc")."""
        return TOOLS[self.tool]

    def parts(self) -> dict[str, tuple[type, str]]:
        """Every config of its runs by name, with its option prefix."""
        return {self.part: (self.config_class(), ""), **self.agent_class().parts}

    def offered(self) -> list[str]:
        """The fields of its run config its command line offers: not ``method``,
        not those it fixes, not those that act only with a value it fixes otherwise."""
        return [n for n in offered(self.config_class(), dict(self.options)) if n != "method"]

    def add_options(self, parser: Any, choices: dict[str, dict[str, Any]] | None = None
                    ) -> None:
        """Its options on ``parser`` (an ArgumentParser): those of its run config
        it offers, then those of its other parts under their prefixes (choices:
        by part, choices of their fields beyond their own)."""
        cls, shown = self.config_class(), set(self.offered())
        first = ("scenario", "seed", "out", "intervals", "steps_per_interval")
        add_dataclass_options(parser, cls, skip=[f.name for f in fields(cls) if f.name not in shown],
                              order=[n for n in first if n in shown])
        for name, (part, prefix) in self.agent_class().parts.items():
            add_dataclass_options(parser.add_argument_group(f"--method {self.name}: {name} options"),
                                  part, prefix, choices=(choices or {}).get(name))

    def config(self, values: Mapping[str, Any]) -> Any:
        """Its run config from option values (its fixed options and name set)."""
        return self.config_class()(**{**values, **self.options, "method": self.name})

    @property
    def args(self) -> tuple[str, ...]:
        """How ``ftc.experiments`` starts its runs (with its tool, :attr:`module`)."""
        return ("--method", self.name, *self.recommended)

    @property
    def module(self) -> str:
        return self.tool

    @property
    def columns(self) -> tuple[str, ...]:
        """The metrics.csv columns its agent adds to the runner's."""
        return tuple(self.agent_class().extra_columns)


METHODS: dict[str, Method] = {}


def register(m: Method) -> Method:
    """Add ``m`` to the methods (a name registered differently is a ValueError)."""
    if m.name in METHODS and METHODS[m.name] is not m:
        raise ValueError(f"method {m.name!r} is already registered")
    if m.name in ALIASES:
        raise ValueError(f"method {m.name!r}: a former name of {ALIASES[m.name]}")
    METHODS[m.name] = m
    return m


_BASELINE = "ftc.control.agents.baselines:BaselineAgent"
_PPO = "ftc.control.agents.ppo:PPOAgent"
_ORACLE = "ftc.control.agents.physics.mpc:OracleMPCAgent"
# the guided methods' recommended settings: pretrained, the guided fit only, the C++ PPO kernel
_GUIDED = ("--pretrain", "--offline-steps", "0", "--ppo-engine", "native")

for _m in (
    Method("closed", _BASELINE, "all valves closed", color="tab:blue"),
    Method("open", _BASELINE, "all valves open", color="tab:orange"),
    Method("random", _BASELINE, "each valve open with p = 1/2", color="tab:gray",
           benchmark=False),
    Method("balance", "ftc.control.agents.balance:BalanceAgent", "rule: balance the wings",
           color="tab:pink"),
    Method("ppo", _PPO, "PPO (Algorithm 1, as its options configure it)",
           knows="the learned model", learns=True, compared=False),
    Method("ppo-online", _PPO, "PPO online", options={"offline": False}, color="tab:green",
           cost=3.0, learns=True),
    Method("ppo-offline", _PPO, "PPO online + offline", options={"offline": True},
           color="tab:red", knows="the learned model", cost=8.0, learns=True),
    Method("ppo-pretrained", _PPO, "PPO online + offline, pretrained",
           options={"offline": True, "pretrain": True}, color="tab:olive",
           knows="the learned model", cost=8.0, learns=True),
    Method("ppo-robust", "ftc.control.agents.physics.ppo_robust:RobustPPOAgent",
           "PPO online + guided offline (robust)", color="tab:brown",
           knows="the plant's equations", recommended=_GUIDED, cost=30.0, learns=True),
    Method("ppo-learned", "ftc.control.agents.learned.ppo_learned:LearnedPPOAgent",
           "PPO online + guided offline on a model learned online", color="#d4a017",
           knows="the learned model",
           # four refits an interval: the model learns a dying pump within the interval,
           # and the policy needs more than ppo-robust's two to follow it (docs/controller.md)
           recommended=(*_GUIDED, "--teacher-refits", "4"), cost=10.0, learns=True),
    # trained once in simulation over a distribution of degradations (DAgger from
    # oracle-mpc), flown without equations; its checkpoint is built by
    # `python -m ftc.experiments.adaptive train` (docs/adaptive.md)
    Method("adaptive-policy", "ftc.control.agents.learned.adaptive_policy:AdaptivePolicyAgent",
           "adaptive student (history window, DAgger in simulation)", color="#2ca58d",
           knows="a simulator of the plant family, for training only", cost=1.0,
           benchmark=False),
    Method("oracle-mpc", _ORACLE, "MPC, faults known (oracle)", tool="ftc.mpc", color="black",
           knows="the true faults", cost=1.5),
    # whole episodes optimised on the true physics (episode_planner.py), never below
    # oracle-mpc's closed loop on the physics it plans with; its margin and cost: docs/benchmarks.md
    Method("reference", _ORACLE, "episode optimisation on the true physics (reference)",
           tool="ftc.mpc", options={"planner": "episode", "rollout_closed_form": True},
           knows="the true faults", cost=20.0, cached=True),
    Method("model-mpc", "ftc.control.agents.physics.mpc:ModelMPCAgent",
           "MPC on the learned model", tool="ftc.mpc", color="tab:purple",
           knows="the learned model", cost=3.0, learns=True),
    Method("learned-mpc", "ftc.control.agents.learned.learned_mpc:LearnedMPCAgent",
           "MPC on a model learned online", tool="ftc.mpc", color="#1f3f99",
           knows="the learned model", cost=2.0, learns=True),
    Method("identified-mpc", "ftc.control.agents.physics.identified_mpc:IdentifiedAgent",
           "MPC on identified physics", tool="ftc.mpc", color="tab:cyan",
           knows="the plant's equations", cost=2.0, learns=True),
):
    register(_m)


def method(name: str) -> Method:
    """The method called ``name`` (or a former name of it); ValueError listing the names."""
    try:
        return METHODS[canonical(name)]
    except KeyError:
        raise ValueError(f"unknown method {name!r}; the methods: {', '.join(METHODS)}") from None


def tool_methods(tool: str) -> tuple[str, ...]:
    """The names ``tool``'s ``--method`` accepts (former names aside)."""
    return tuple(m.name for m in METHODS.values() if m.tool == tool)


def colors() -> dict[str, str]:
    """Each method's colour in figures."""
    return {m.name: m.color for m in METHODS.values() if m.color}


def agent_for(configs: dict[str, Any], method_name: str) -> Any:
    """The agent of a run whose config says ``method_name``, built from its configs."""
    return method(method_name).agent_class().from_configs(configs)


def tool_fields(tool: str) -> set[str]:
    """Every field of the run configs of ``tool``'s methods (what its stored runs may hold)."""
    return {f.name for m in METHODS.values() if m.tool == tool for f in fields(m.config_class())}


def _load(path: str) -> Any:
    module, attribute = path.split(":")
    return getattr(importlib.import_module(module), attribute)
