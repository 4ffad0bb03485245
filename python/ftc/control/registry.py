"""The one list of methods: for each controller, the name every tool knows it
by (``ftc.controller --method``, ``ftc.mpc --method``, ``ftc.experiments
--methods``), the agent that runs it, its config class, what it is told about
the plant, its label, the tool and arguments that run it, and how the
experiments schedule it.

A leaf of the control room: the agents and their configs are named as
``"module:attribute"`` and imported only when a run needs them, so listing
the methods imports neither torch nor the native core. A new controller is
its file plus one :class:`Method` line in :data:`METHODS`.
"""

from __future__ import annotations

import importlib
import sys
from dataclasses import dataclass
from typing import Any, Sequence

# What a method is told about the plant, from least to most.
KNOWS = ("nothing", "the learned model", "the plant's equations", "the true faults")
TOOLS = ("ftc.controller", "ftc.mpc")


@dataclass(frozen=True)
class Method:
    """A controller, as every tool names and runs it.

    name: on every command line and in result paths; label: legend text in
    figures and tables; tool: the module run with ``python -m``; args: what
    ``--method NAME`` means on that tool's command line (its own
    ``--method`` value and the flags that make the variant); agent: the
    ``"module:Class"`` whose ``from_configs(configs)`` builds the agent,
    empty for a variant of another method (args name it); config: the
    ``"module:Class"`` of its run config; knows: one of :data:`KNOWS`;
    experiment_args: what ``ftc.experiments`` adds to its runs; cost:
    relative wall time (scheduling, ETA); learns: a learned policy or model
    (deterministic evaluation, model R^2); benchmark: run by ``ftc.experiments
    benchmark`` by default; compared: offered to ``ftc.experiments`` (False:
    a tool-level method whose variants are compared instead); cached: its results
    depend on the scenario only (deterministic planning on the true physics), so
    the benchmark runs it once per scenario and keeps the run."""

    name: str
    label: str
    tool: str
    args: tuple[str, ...]
    agent: str
    config: str
    knows: str = "nothing"
    experiment_args: tuple[str, ...] = ()
    cost: float = 1.0
    learns: bool = False
    benchmark: bool = True
    compared: bool = True
    cached: bool = False

    def __post_init__(self) -> None:
        if self.knows not in KNOWS:
            raise ValueError(f"method {self.name}: knows {self.knows!r}, not one of {KNOWS}")
        if self.tool not in TOOLS:
            raise ValueError(f"method {self.name}: tool {self.tool!r}, not one of {TOOLS}")

    @property
    def tool_method(self) -> str:
        """The value of its tool's ``--method`` (its config's ``method`` field)."""
        return self.args[1]

    def agent_class(self) -> type:
        return _load(METHODS[self.tool_method].agent if not self.agent else self.agent)

    def config_class(self) -> type:
        return _load(self.config)

    @property
    def columns(self) -> tuple[str, ...]:
        """The metrics.csv columns its agent adds to the runner's."""
        return tuple(self.agent_class().extra_columns)


_CONTROLLER = "ftc.control.agents.ppo:ControllerConfig"
_ROBUST = "ftc.control.agents.learned.guided_ppo:GuidedConfig"
_MPC = "ftc.control.agents.mpc_config:MPCConfig"
_BASELINE = "ftc.control.agents.baselines:BaselineAgent"

METHODS: dict[str, Method] = {m.name: m for m in (
    Method("closed", "all valves closed", "ftc.controller", ("--method", "closed"), _BASELINE,
           _CONTROLLER),
    Method("open", "all valves open", "ftc.controller", ("--method", "open"), _BASELINE,
           _CONTROLLER),
    Method("random", "each valve open with p = 1/2", "ftc.controller", ("--method", "random"),
           _BASELINE, _CONTROLLER, benchmark=False),
    Method("balance", "rule: balance the wings", "ftc.controller", ("--method", "balance"),
           "ftc.control.agents.balance:BalanceAgent", _CONTROLLER),
    Method("ppo", "PPO (Algorithm 1, as its flags configure it)", "ftc.controller",
           ("--method", "ppo"), "ftc.control.agents.ppo:PPOAgent", _CONTROLLER,
           knows="the learned model", learns=True, compared=False),
    Method("ppo-online", "PPO online", "ftc.controller", ("--method", "ppo", "--no-offline"),
           "", _CONTROLLER, knows="nothing", cost=3.0, learns=True),
    Method("ppo-offline", "PPO online + offline", "ftc.controller",
           ("--method", "ppo", "--offline"), "", _CONTROLLER, knows="the learned model",
           cost=8.0, learns=True),
    Method("ppo-pretrained", "PPO online + offline, pretrained", "ftc.controller",
           ("--method", "ppo", "--offline", "--pretrain"), "", _CONTROLLER,
           knows="the learned model", cost=8.0, learns=True),
    Method("ppo-robust", "PPO online + guided offline (robust)", "ftc.controller",
           ("--method", "ppo-robust"), "ftc.control.agents.physics.ppo_robust:RobustPPOAgent", _ROBUST,
           knows="the plant's equations",
           experiment_args=("--pretrain", "--offline-steps", "0", "--ppo-engine", "native"),
           cost=30.0, learns=True),
    Method("ppo-learned", "PPO online + guided offline on a model learned online",
           "ftc.controller", ("--method", "ppo-learned"),
           "ftc.control.agents.learned.ppo_learned:LearnedPPOAgent", _ROBUST, knows="the learned model",
           # four refits an interval: the model learns a dying pump within the interval,
           # and the policy needs more than ppo-robust's two to follow it (docs/controller.md)
           experiment_args=("--pretrain", "--offline-steps", "0", "--ppo-engine", "native",
                            "--teacher-refits", "4"),
           cost=10.0, learns=True),
    Method("oracle-mpc", "MPC, faults known (oracle)", "ftc.mpc", ("--method", "oracle-mpc"),
           "ftc.control.agents.physics.mpc:MPCAgent", _MPC, knows="the true faults", cost=1.5),
    # whole episodes optimised on the true physics (episode_planner.py), never below
    # oracle-mpc's closed loop on the physics it plans with; its margin and cost: docs/benchmarks.md
    Method("reference", "episode optimisation on the true physics (reference)", "ftc.mpc",
           ("--method", "oracle-mpc", "--planner", "episode", "--rollout-closed-form"), "", _MPC,
           knows="the true faults", cost=20.0, cached=True),
    Method("model-mpc", "MPC on the learned model", "ftc.mpc", ("--method", "model-mpc"),
           "ftc.control.agents.physics.mpc:MPCAgent", _MPC, knows="the learned model", cost=3.0,
           learns=True),
    Method("learned-mpc", "MPC on a model learned online", "ftc.mpc", ("--method", "learned-mpc"),
           "ftc.control.agents.learned.learned_mpc:LearnedMPCAgent", _MPC, knows="the learned model", cost=2.0,
           learns=True),
    Method("identified-mpc", "MPC on identified physics", "ftc.mpc",
           ("--method", "identified-mpc"), "ftc.control.agents.physics.identified_mpc:IdentifiedAgent", _MPC,
           knows="the plant's equations", cost=2.0, learns=True),
)}

# Former tool-local names, accepted (with a warning) and read from older run
# directories and results.
ALIASES = {"oracle": "oracle-mpc", "model": "model-mpc", "adaptive": "identified-mpc"}


def canonical(name: str) -> str:
    """The registry's name for ``name`` (an alias mapped; anything else unchanged)."""
    return ALIASES.get(name, name)


def method(name: str) -> Method:
    """The method called ``name`` (or an alias of it); ValueError listing the names."""
    try:
        return METHODS[canonical(name)]
    except KeyError:
        raise ValueError(f"unknown method {name!r}; the methods: {', '.join(METHODS)}") from None


def tool_methods(tool: str) -> tuple[str, ...]:
    """The names ``tool``'s ``--method`` accepts (aliases aside)."""
    return tuple(m.name for m in METHODS.values() if m.tool == tool)


def config_values(tool: str) -> tuple[str, ...]:
    """The values of ``tool``'s config ``method`` field (the methods with an agent)."""
    return tuple(m.name for m in METHODS.values() if m.tool == tool and m.agent)


def guided_methods() -> tuple[str, ...]:
    """The methods whose runs take the guided fit's options (ppo-robust, ppo-learned)."""
    return tuple(m.name for m in METHODS.values() if m.config == _ROBUST)


def policy_methods(tool: str = "ftc.controller") -> tuple[str, ...]:
    """The config ``method`` values of ``tool`` whose agent learns a policy (PPO's
    options act on them; the other methods refuse them)."""
    return tuple(m.name for m in METHODS.values() if m.tool == tool and m.agent and m.learns)


def agent_for(configs: dict[str, Any], method_name: str) -> Any:
    """The agent of a run whose config says ``method_name``, built from its configs."""
    return method(method_name).agent_class().from_configs(configs)


def expand_method(argv: Sequence[str], tool: str) -> list[str]:
    """``argv`` with ``--method NAME`` replaced by what NAME means on ``tool``'s
    command line (``--method ppo-offline`` -> ``--method ppo --offline``); an
    alias warns on stderr and maps. ValueError: a method of another tool, an
    unknown one, or a flag the method fixes given as well."""
    argv = list(argv)
    for i, word in enumerate(argv):
        if word == "--method" and i + 1 < len(argv):
            start, name = i, argv[i + 1]
            end = i + 2
        elif word.startswith("--method="):
            start, name, end = i, word.split("=", 1)[1], i + 1
        else:
            continue
        if name in ALIASES:
            print(f"{tool}: warning: --method {name} is deprecated; use --method "
                  f"{ALIASES[name]}", file=sys.stderr, flush=True)
        if canonical(name) not in METHODS:
            others = [t for t in TOOLS if t != tool]
            raise ValueError(f"--method {name}: unknown; {tool} runs "
                             f"{', '.join(tool_methods(tool))} (and "
                             + "; ".join(f"{t}: {', '.join(tool_methods(t))}" for t in others)
                             + ")")
        m = method(name)
        if m.tool != tool:
            raise ValueError(f"--method {m.name} is run by {m.tool}, not {tool}")
        rest = argv[:start] + argv[end:]
        for fixed in m.args[2:]:
            stem = fixed.removeprefix("--no-").removeprefix("--")
            given = [w.split("=", 1)[0] for w in rest
                     if w.split("=", 1)[0] in (f"--{stem}", f"--no-{stem}")]
            if given:
                raise ValueError(f"{given[0]} is fixed by --method {m.name} "
                                 f"(it means {' '.join(m.args)}); give --method "
                                 f"{m.tool_method} to choose it")
        return argv[:start] + list(m.args) + argv[end:]
    return argv


def _load(path: str) -> Any:
    module, attribute = path.split(":")
    return getattr(importlib.import_module(module), attribute)
