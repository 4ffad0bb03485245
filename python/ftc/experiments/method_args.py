"""Which of an experiment's extra controller arguments (--controller-args,
--pretrain) the runs of each method get.

Each option (a ``--flag`` and the values after it) goes to the methods whose
command line has it and on which it acts: an ``ftc.mpc`` method gets the
MPC options that act on it (``--model-episodes`` reaches model-mpc only,
``--identify-every`` identified-mpc), a PPO method of ``ftc.controller`` all of the controller's, and a
baseline of ``ftc.controller`` only the options every run shares (the link,
the console), since it refuses PPO options as having no effect. An option no
chosen method takes is refused before anything runs.
"""

from __future__ import annotations

import argparse
import functools
import importlib
from dataclasses import fields
from typing import Any, Callable, Sequence

from ftc.common.cli import add_dataclass_options, config_from_namespace
from ftc.control import registry
from ftc.control.agents.learned.guided_ppo import GUIDED_FIELDS as ROBUST_FIELDS, GuidedConfig as RobustConfig
from ftc.control.agents.mpc_config import MPCConfig
from ftc.control.agents.plugins import PluginConfig
from ftc.control.run.config import RunConfig
from ftc.experiments.methods import METHODS, MethodSpec
from ftc.learning.ppo import PPOConfig

# The config parts (class, option prefix) each method's module reads its command line into.
PARTS = {"ftc.controller": ((RobustConfig, ""), (PPOConfig, "ppo-")), "ftc.mpc": ((MPCConfig, ""),),
         "ftc.plugin": ((PluginConfig, ""),)}


def tool_parser(module: str) -> Callable[[Sequence[str]], Any] | None:
    """The ``parse_args`` of the tool a method's runs are started with
    (``python -m MODULE``), loaded by that name as the runs are, to check their
    command lines in process; None for a module of another kind."""
    if module not in PARTS:
        return None
    return importlib.import_module(module).parse_args


def _parser(module: str) -> argparse.ArgumentParser:
    """The options of ``module``'s command line, from its config parts."""
    parser = argparse.ArgumentParser(add_help=False)
    for cls, prefix in PARTS[module]:
        add_dataclass_options(parser, cls, prefix)
    return parser


def option_groups(extra: Sequence[str]) -> list[list[str]]:
    """``--a 1 2 --b --c=3`` -> [["--a", "1", "2"], ["--b"], ["--c=3"]]; words
    before the first option form a group of their own (taken by no method)."""
    groups: list[list[str]] = []
    for word in extra:
        if word.startswith("--") or not groups:
            groups.append([word])
        else:
            groups[-1].append(word)
    return groups


@functools.cache
def _flags(module: str) -> tuple[frozenset[str], frozenset[str]]:
    """(every option of the module's command line, those of RunConfig's fields)."""
    parser = _parser(module)
    shared = {f.name for f in fields(RunConfig)}
    every, run = set(), set()
    for action in parser._actions:  # noqa: SLF001 - the parser's own options
        every.update(action.option_strings)
        if action.dest in shared:
            run.update(action.option_strings)
    return frozenset(every), frozenset(run)


def takes(spec: MethodSpec, option: str) -> bool:
    """Whether the runs of ``spec`` get ``option`` (a flag, ``--x`` or ``--x=v``)."""
    if spec.module not in PARTS:  # a module of another kind: it gets everything
        return True
    every, run = _flags(spec.module)
    flag = option.split("=", 1)[0]
    if flag not in every:
        return False
    if flag in run:
        return True
    if spec.module == "ftc.plugin":  # its own options: --agent is its spec, and
        # --sb3-learn acts on an sb3: model only
        return flag == "--sb3-learn" and spec.args[-1].startswith("sb3:")
    parsed = _parsed(spec)
    dest = flag[2:].replace("-", "_").removeprefix("no_")
    if dest in parsed.ignored():
        return False
    if spec.module == "ftc.mpc":
        return True
    return spec.learns and (parsed.method in registry.guided_methods() or dest not in ROBUST_FIELDS)


@functools.cache
def _parsed(spec: MethodSpec):
    """The config a run of ``spec`` gets from its own arguments (what ignores what)."""
    ns = vars(_parser(spec.module).parse_args(registry.expand_method(spec.args, spec.module)))
    if spec.module == "ftc.mpc":
        return config_from_namespace(MPCConfig, ns)
    # the controller's own options (its --ppo-* options configure PPOConfig)
    values = vars(config_from_namespace(RobustConfig, ns))
    cls = registry.method(values["method"]).config_class()
    return cls(**{f.name: values[f.name] for f in fields(cls)})


def method_args(spec: MethodSpec, extra: Sequence[str]) -> list[str]:
    """The extra arguments the runs of ``spec`` get, in the order given."""
    return [w for g in option_groups(extra) if takes(spec, g[0]) for w in g]


def untaken(methods: Sequence[str], extra: Sequence[str]) -> list[str]:
    """The options of ``extra`` that none of ``methods`` takes."""
    return [g[0] for g in option_groups(extra)
            if not any(takes(METHODS[m], g[0]) for m in methods)]
