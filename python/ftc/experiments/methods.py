"""The compared methods: how each controller of the experiments is started,
a view of :mod:`ftc.control.registry` (one name per method in every tool).
A method of another module (a plug-in) joins with :func:`register_method`.
"""

from __future__ import annotations

from dataclasses import dataclass

from ftc.control import registry


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
        register_method(MethodSpec(_m.name, _m.label, ("--method", _m.name, *_m.experiment_args),
                                   module=_m.tool, cost=_m.cost, learns=_m.learns,
                                   benchmark=_m.benchmark, cached=_m.cached))
PAPER_METHODS = ("closed", "open", "ppo-online", "ppo-offline")
DEFAULT_METHODS = (*PAPER_METHODS, "oracle-mpc", "model-mpc")
