"""Controllers from outside the package, named by a spec instead of a registry name.

    module.path:factory   a user's Agent: ``factory(cfg)`` (``factory()`` when it has
                          no parameter without a default) returns
                          an :class:`ftc.control.run.agent.Agent` (the protocol of
                          docs/architecture.md, API version :data:`API_VERSION`);
                          cfg is the run's :class:`PluginConfig` (seed, scenario, ...)
    sb3:PATH.zip          a Stable-Baselines3 policy (PPO or A2C, as
                          examples/sb3_ppo.py saves it), acting deterministically
                          on the published levels; with --sb3-learn fine-tuned on
                          the plant as it runs (:mod:`ftc.control.agents.sb3`)
    onnx:PATH.onnx        a policy exported by ``ftc.export``, or any ONNX model
                          with its input (levels, float32 [N, 6], metres) and an
                          output of 0/1 valves [N, 6] (named ``valves``, or its first)

A bad spec is a :class:`PluginError` naming the module, attribute or file.
"""

from __future__ import annotations

import importlib
import inspect
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ftc.common.constants import NUM_TANKS, TANK_HEIGHT
from ftc.common.errors import RunError, UsageError
from ftc.control.run.agent import Agent, StepContext
from ftc.control.run.config import RunConfig
from ftc.plant.link import PlantObservation
from ftc.plant.valves import valves_problem

API_VERSION = 1  # the Agent protocol a plug-in is written against
KINDS = ("module.path:factory", "sb3:PATH.zip", "onnx:PATH.onnx")
NAME = r"[A-Za-z0-9][A-Za-z0-9_.-]*"  # what a method's name may hold (it names paths)


class PluginError(ValueError):
    """A spec that does not give a controller; the message says what and where."""


class PluginActionError(UsageError):
    """A plug-in answered with something other than six valves of 0 or 1 (exit 2)."""


class PluginFailedError(RunError):
    """A plug-in raised while acting (exit 1)."""


def guard_actions(agent: Agent, spec: str) -> Agent:
    """``agent`` with every action checked before the plant sees it: a plug-in's
    invalid action (another shape, NaN, 2, -1, 0.5) or its exception ends the
    run with one line naming the plug-in, the interval and the step."""
    act = agent.act

    def checked(obs: PlantObservation, ctx: StepContext) -> np.ndarray:
        where = (f"plug-in {spec} at interval {ctx.interval}, "
                 f"{'evaluation ' if ctx.evaluation else ''}step {ctx.step}")
        try:
            u = act(obs, ctx)
        except PluginError as e:  # a policy's own check (_checked), which names the spec
            raise PluginActionError(f"{where}: {str(e).removeprefix(spec + ': ')}") from None
        except Exception as e:  # noqa: BLE001 - the plug-in's own failure, named
            reason = str(e).strip().splitlines()[0] if str(e).strip() else ""
            raise PluginFailedError(f"{where} raised {type(e).__name__}: {reason[:200]}") from None
        problem = valves_problem(u)
        if problem is not None:
            raise PluginActionError(f"{where}: the action {problem} (six valves, each 0 or 1)")
        return np.asarray(u).astype(np.int8)

    agent.act = checked  # type: ignore[method-assign]
    return agent


@dataclass
class PluginConfig(RunConfig):
    """A run of a plug-in controller: the run's options and the spec."""

    agent: str = field(default="", metadata={"help": (
        "the controller: module.path:factory (a user's Agent), sb3:PATH.zip (an SB3 policy) "
        "or onnx:PATH.onnx (an exported policy)")})
    out: str = field(default="runs/plugin", metadata={"help": "output directory"})
    sb3_learn: bool = field(default=False, metadata={"help": (
        "sb3:PATH.zip only: fine-tune the model on the plant as it runs (its actions "
        "sampled, its own train() every n_steps plant steps); the evaluation episode "
        "acts deterministically")})

    def validate(self) -> None:
        super().validate()
        name, spec = split_name(self.agent)
        if name is not None and not re.fullmatch(NAME, name):
            raise ValueError(f"{self.agent}: the name {name!r} may hold letters, digits and "
                             ". _ - only")
        if self.sb3_learn and not spec.startswith("sb3:"):
            raise ValueError(f"--sb3-learn fine-tunes an sb3:PATH.zip model, not {self.agent!r}")
        if not is_plugin(self.agent):
            raise ValueError(f"{self.agent!r} is not a plug-in spec ([NAME=]SPEC, SPEC one of "
                             f"{', '.join(KINDS)})")


def is_plugin(spec: str) -> bool:
    """Whether ``spec`` (or ``NAME=SPEC``) names a plug-in (registry names hold no colon)."""
    return ":" in spec


def split_name(entry: str) -> tuple[str | None, str]:
    """``NAME=SPEC`` -> (NAME, SPEC); ``SPEC`` -> (None, SPEC). A NAME is what
    stands before an ``=`` ahead of the spec's first ``:`` (a path may hold ``=``)."""
    name, eq, spec = entry.partition("=")
    return (name, spec) if eq and ":" not in name else (None, entry)


def default_name(spec: str) -> str:
    """The name a plug-in's results go under when none is given: the factory's
    name, or the file's stem, in the characters a method name may hold."""
    kind, _, rest = spec.partition(":")
    base = Path(rest).stem if kind in ("sb3", "onnx") else rest.rsplit(".", 1)[-1]
    return re.sub(r"[^A-Za-z0-9_.-]+", "-", base).strip("-.") or "plugin"


class PolicyAgent(Agent):
    """An agent acting with a fixed policy: levels (6,) m -> valves (6,) 0/1."""

    evaluates = True

    def __init__(self, name: str, policy: Callable[[np.ndarray], np.ndarray]) -> None:
        self.name, self.policy = name, policy

    def act(self, obs: PlantObservation, ctx: StepContext) -> np.ndarray:
        return self.policy(np.asarray(obs.level, np.float32))


def load_agent(entry: str, cfg: PluginConfig) -> Agent:
    """The agent ``entry`` ([NAME=]SPEC) names, going by NAME when given;
    PluginError saying what is wrong and where."""
    name, spec = split_name(entry)
    kind, _, rest = spec.partition(":")
    if kind == "sb3":
        model = _sb3_model(Path(rest))
        policy = _checked(lambda levels: model.predict(levels, deterministic=True)[0], spec)
        if cfg.sb3_learn:
            from ftc.control.agents.sb3 import SB3Agent  # torch: only an agent that learns

            return SB3Agent(name or default_name(spec), model)
        return PolicyAgent(name or default_name(spec), policy)
    if kind == "onnx":
        return PolicyAgent(name or default_name(spec), _checked(_onnx_policy(Path(rest)), spec))
    agent = _factory_agent(kind, rest, cfg)
    if name is not None:
        agent.name = name
    return agent


def _factory_agent(module_name: str, attribute: str, cfg: PluginConfig) -> Agent:
    try:
        module = importlib.import_module(module_name)
    except Exception as e:  # noqa: BLE001 - any import failure is the user's module's
        raise PluginError(f"cannot import module {module_name!r}: {type(e).__name__}: {e}")
    factory = getattr(module, attribute, None)
    if not callable(factory):
        raise PluginError(f"module {module_name!r} has no callable {attribute!r}")
    try:  # factory(cfg) where it has a parameter to fill, factory() where all are optional
        takes_config = any(p.default is inspect.Parameter.empty and p.kind in (
            p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)
            for p in inspect.signature(factory).parameters.values())
    except (TypeError, ValueError):
        takes_config = True
    try:
        agent = factory(cfg) if takes_config else factory()
    except Exception as e:  # noqa: BLE001 - the factory's own failure, named
        raise PluginError(f"{module_name}:{attribute} failed: {type(e).__name__}: {e}")
    if not callable(getattr(agent, "act", None)):
        raise PluginError(f"{module_name}:{attribute} returned {type(agent).__name__}, not an "
                          "Agent (it has no act(obs, ctx))")
    return agent


def _library(kind: str, path: Path, module: str) -> Any:
    """The library that reads a ``kind`` file, once the file is there; PluginError
    naming the missing file or library."""
    if not path.is_file():
        raise PluginError(f"{kind}:{path}: no such file")
    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise PluginError(f"{kind}:{path}: {module} is not installed ({e})")


def _sb3_model(path: Path) -> Any:
    sb3 = _library("sb3", path, "stable_baselines3")
    PPO, A2C = sb3.PPO, sb3.A2C
    errors = []
    for algorithm in (PPO, A2C):
        try:
            model = algorithm.load(str(path), device="cpu")
            break
        except Exception as e:  # noqa: BLE001 - not this algorithm's file: try the next
            errors.append(f"{algorithm.__name__}: {type(e).__name__}: {e}")
    else:
        raise PluginError(f"sb3:{path}: not a PPO or A2C model ({'; '.join(errors)})")
    return model


def _onnx_policy(path: Path) -> Callable[[np.ndarray], np.ndarray]:
    onnxruntime = _library("onnx", path, "onnxruntime")
    try:
        session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    except Exception as e:  # noqa: BLE001 - a corrupt or foreign file
        raise PluginError(f"onnx:{path}: not a readable ONNX model ({type(e).__name__}: "
                          f"{str(e).splitlines()[0] if str(e) else ''})")
    inputs, outputs = session.get_inputs(), [o.name for o in session.get_outputs()]
    if len(inputs) != 1:
        raise PluginError(f"onnx:{path}: {len(inputs)} inputs; the policy takes one, the "
                          "levels [N, 6]")
    name, output = inputs[0].name, "valves" if "valves" in outputs else outputs[0]
    shape = inputs[0].shape or []
    if len(shape) != 2 or (isinstance(shape[-1], int) and shape[-1] != NUM_TANKS):
        raise PluginError(f"onnx:{path}: input {name!r} has shape {list(shape)}; the policy "
                          f"takes the levels [N, {NUM_TANKS}]")
    return lambda levels: session.run([output], {name: levels[None]})[0][0]


def _checked(policy: Callable[[np.ndarray], np.ndarray], spec: str
             ) -> Callable[[np.ndarray], np.ndarray]:
    """The policy, as 0/1 int8 valves, once it answered full tanks with six of them."""
    def valves(levels: np.ndarray) -> np.ndarray:
        u = np.asarray(policy(levels)).reshape(-1)
        problem = valves_problem(u)
        if problem is not None:
            raise PluginError(f"{spec}: the policy's action {problem} (six valves, each 0 or 1)")
        return u.astype(np.int8)

    try:
        valves(np.full(NUM_TANKS, TANK_HEIGHT, np.float32))
    except PluginError:
        raise
    except Exception as e:  # noqa: BLE001 - the model's own failure on a valid input
        reason = str(e).strip().splitlines()[0] if str(e).strip() else ""
        raise PluginError(f"{spec}: the policy fails on full tanks: {type(e).__name__}: "
                          f"{reason[:200]}")
    return valves
