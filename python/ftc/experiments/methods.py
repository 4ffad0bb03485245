"""The compared methods: how each controller of the experiments is started,
a view of :mod:`ftc.control.registry` (one name per method in every tool).
A method of another module (a plug-in) joins with :func:`register_method`.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from ftc.control import registry
from ftc.control.agents import plugins


@dataclass(frozen=True)
class MethodSpec:
    """A compared method: a module run with ``python -m`` and its method arguments.

    The module must accept the controller's common options (--scenario, --seed,
    --out, --intervals, --steps-per-interval, --lcm-url, --prefix; --tensorboard
    DIR when ftc.experiments is given one) and write OUT/metrics.csv (one row
    per interval) like ``ftc.controller`` does.

    name: identifier used on the command line and in paths
    label: legend text in figures and tables
    args: method-specific arguments
    module: the Python module to run
    cost: relative wall time (for scheduling longest first and the ETA)
    learns: whether it has a learned policy (deterministic evaluation, model R^2)
    benchmark: whether ``ftc.experiments benchmark`` runs it by default (False for
        diagnostic or very slow variants)
    cached: its results depend on the scenario only: the benchmark runs it once per
        scenario and keeps the run (:mod:`ftc.experiments.run_cache`)
    """

    name: str
    label: str
    args: tuple[str, ...]
    module: str = "ftc.controller"
    cost: float = 1.0
    learns: bool = False
    benchmark: bool = True
    cached: bool = False


METHODS: dict[str, MethodSpec] = {}


def register_method(spec: MethodSpec) -> MethodSpec:
    """Make a method available by name (e.g. an MPC oracle, a learned-model MPC)."""
    if spec.name in METHODS and METHODS[spec.name] != spec:
        raise ValueError(f"method '{spec.name}' is already registered differently")
    METHODS[spec.name] = spec
    return spec


for _m in registry.METHODS.values():
    if _m.compared:  # the experiments run each under its own name: --method NAME
        register_method(MethodSpec(_m.name, _m.label, _m.args, module=_m.tool, cost=_m.cost,
                                   learns=_m.learns, benchmark=_m.benchmark, cached=_m.cached))

PLUGIN_MODULE = "ftc.plugin"  # the tool that runs a plug-in (ftc.tools.plugin)


def plugin_method(entry: str) -> MethodSpec:
    """A plug-in entry of --methods, ``NAME=SPEC`` or ``SPEC`` (NAME: the factory's
    name or the file's stem), registered under NAME once its spec has given an
    agent; ValueError naming what is wrong (the module, attribute or file)."""
    name, spec = plugins.split_name(entry)
    if name is None:
        name = plugins.default_name(entry)
    if not plugins.is_plugin(spec):
        raise ValueError(f"{entry}: not a method name nor a plug-in (NAME=SPEC, SPEC one of "
                         f"{', '.join(plugins.KINDS)})")
    if not re.fullmatch(plugins.NAME, name):
        raise ValueError(f"{entry}: the name {name!r} may hold letters, digits and . _ - only")
    if name in registry.METHODS:
        raise ValueError(f"{entry}: {name} is a built-in method; name the plug-in NAME={spec}")
    kind, _, path = spec.partition(":")
    if kind in ("sb3", "onnx"):  # the runs start elsewhere: an absolute path
        spec = f"{kind}:{Path(path).expanduser().resolve()}"
    try:
        plugins.load_agent(spec, plugins.PluginConfig(agent=spec, scenario=None))
    except plugins.PluginError as e:
        raise ValueError(str(e)) from None
    return register_method(MethodSpec(name, f"plug-in {spec}", ("--agent", spec),
                                      module=PLUGIN_MODULE, benchmark=False))


def resolve_methods(entries: Sequence[str] | None, stored: Path | None) -> list[str] | None:
    """--methods as names: plug-in entries registered (:func:`plugin_method`), and
    the plug-ins of a stored run directory's metadata (``stored``: its JSON file,
    when it exists) registered again for a --resume; ValueError as plugin_method."""
    if stored is not None and stored.is_file():
        try:
            recorded = json.loads(stored.read_text()).get("methods", {})
        except (OSError, ValueError, AttributeError):
            recorded = {}  # the tool's own check of the file names what is wrong
        for spec in recorded.values():
            if isinstance(spec, dict) and spec.get("module") == PLUGIN_MODULE:
                register_method(MethodSpec(**{**spec, "args": tuple(spec["args"])}))
    if entries is None:
        return None
    return [e if e in METHODS else plugin_method(e).name if ("=" in e or ":" in e) else e
            for e in entries]


PAPER_METHODS = ("closed", "open", "ppo-online", "ppo-offline")
DEFAULT_METHODS = (*PAPER_METHODS, "oracle-mpc", "model-mpc")
