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

from ftc.common.cli import add_dataclass_options, unmet
from ftc.control import registry
from ftc.control.agents.plugins import PluginConfig
from ftc.control.run.config import RunConfig
from ftc.experiments.methods import METHODS, MethodSpec

PLUGIN = "ftc.plugin"  # the tool of the plug-ins (its options: PluginConfig's)


def tool_parser(module: str) -> Callable[[Sequence[str]], Any] | None:
    """The ``parse_args`` of the tool a method's runs are started with
    (``python -m MODULE``), loaded by that name as the runs are, to check their
    command lines in process; None for a module of another kind."""
    if module not in registry.TOOLS and module != PLUGIN:
        return None
    return importlib.import_module(module).parse_args


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
def _parser(name: str) -> argparse.ArgumentParser:
    """The options of a run of ``name`` (a registry method's, or a plug-in's)."""
    parser = argparse.ArgumentParser(add_help=False)
    if name == PLUGIN:
        add_dataclass_options(parser, PluginConfig)
    else:
        parser.add_argument("--method")
        registry.method(name).add_options(parser)
    return parser


def _flags(parser: argparse.ArgumentParser) -> tuple[frozenset[str], frozenset[str]]:
    """(every option of ``parser``, those of RunConfig's fields)."""
    shared = {f.name for f in fields(RunConfig)}
    every, run = set(), set()
    for action in parser._actions:  # noqa: SLF001 - the parser's own options
        every.update(action.option_strings)
        if action.dest in shared:
            run.update(action.option_strings)
    return frozenset(every), frozenset(run)


def takes(spec: MethodSpec, option: str) -> bool:
    """Whether the runs of ``spec`` get ``option`` (a flag, ``--x`` or ``--x=v``):
    an option its command line offers and that acts on it as its own arguments
    configure it."""
    if spec.module not in registry.TOOLS and spec.module != PLUGIN:
        return True  # a module of another kind: it gets everything
    plugin = spec.module == PLUGIN
    every, run = _flags(_parser(PLUGIN if plugin else spec.name))
    flag = option.split("=", 1)[0]
    if flag not in every or flag == "--method":
        return False
    if flag in run:
        return True
    if plugin:  # its own options: --agent is its spec, and --sb3-learn acts on an sb3: model only
        return flag == "--sb3-learn" and spec.args[-1].startswith("sb3:")
    dest = flag[2:].replace("-", "_").removeprefix("no_")
    return dest not in unmet(_parsed(spec.name))


@functools.cache
def _parsed(name: str) -> Any:
    """The run config a run of method ``name`` gets from its own arguments."""
    m = registry.method(name)
    ns = vars(_parser(name).parse_known_args(list(m.args))[0])
    return m.config({n: ns[n] for n in m.offered()})


def method_args(spec: MethodSpec, extra: Sequence[str]) -> list[str]:
    """The extra arguments the runs of ``spec`` get, in the order given."""
    return [w for g in option_groups(extra) if takes(spec, g[0]) for w in g]


def untaken(methods: Sequence[str], extra: Sequence[str]) -> list[str]:
    """The options of ``extra`` that none of ``methods`` takes."""
    return [g[0] for g in option_groups(extra)
            if not any(takes(METHODS[m], g[0]) for m in methods)]
