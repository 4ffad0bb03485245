"""The compared methods: how each controller of the experiments is started.

A leaf module (it imports nothing of ftc), so the orchestrator, the figures
and the report all read the one registry. Add a method with
:func:`register_method`.
"""

from __future__ import annotations

from dataclasses import dataclass


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
    """

    name: str
    label: str
    args: tuple[str, ...]
    module: str = "ftc.controller"
    cost: float = 1.0
    learns: bool = False
    benchmark: bool = True


METHODS: dict[str, MethodSpec] = {}


def register_method(spec: MethodSpec) -> MethodSpec:
    """Make a method available by name (e.g. an MPC oracle, a learned-model MPC)."""
    if spec.name in METHODS and METHODS[spec.name] != spec:
        raise ValueError(f"method '{spec.name}' is already registered differently")
    METHODS[spec.name] = spec
    return spec


register_method(MethodSpec("closed", "all valves closed", ("--method", "closed"), cost=1.0))
register_method(MethodSpec("open", "all valves open", ("--method", "open"), cost=1.0))
register_method(MethodSpec("ppo-online", "PPO online", ("--method", "ppo", "--no-offline"),
                           cost=3.0, learns=True))
register_method(MethodSpec("ppo-offline", "PPO online + offline",
                           ("--method", "ppo", "--offline"), cost=8.0, learns=True))
register_method(MethodSpec("ppo-pretrained", "PPO online + offline, pretrained",
                           ("--method", "ppo", "--offline", "--pretrain"), cost=8.0, learns=True))
register_method(MethodSpec("oracle-mpc", "MPC, faults known (oracle)", ("--method", "oracle"),
                           module="ftc.mpc", cost=1.5))
register_method(MethodSpec("model-mpc", "MPC on the learned model", ("--method", "model"),
                           module="ftc.mpc", cost=3.0, learns=True))
register_method(MethodSpec("balance", "rule: balance the wings", ("--method", "balance"),
                           cost=1.0))
register_method(MethodSpec("ppo-robust", "PPO online + guided offline (robust)",
                           ("--method", "ppo-robust", "--pretrain", "--offline-steps", "0",
                            "--ppo-engine", "native"),
                           cost=30.0, learns=True))
register_method(MethodSpec("adaptive", "MPC on identified physics (adaptive)",
                           ("--method", "adaptive"), module="ftc.mpc", cost=2.0, learns=True))
PAPER_METHODS = ("closed", "open", "ppo-online", "ppo-offline")
DEFAULT_METHODS = (*PAPER_METHODS, "oracle-mpc", "model-mpc")
