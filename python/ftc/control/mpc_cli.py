"""``python -m ftc.mpc``: the two MPC reference controllers on the interval
runner (see :mod:`ftc.control.mpc_agent` for what they do)."""

from __future__ import annotations

import argparse
import sys
from typing import Any, Sequence

import torch

from ftc.common.cli import OneLineParser, config_from_namespace
from ftc.control import mpc_agent
from ftc.control.cli import add_run_options, check_or_exit, read_run_configs, run_or_report
from ftc.control.adaptive_agent import AdaptiveAgent
from ftc.control.mpc_agent import MPCAgent, MPCConfig
from ftc.control.runner import IntervalRunner

TOOL = "ftc.mpc"


class MPCController(IntervalRunner):
    """An MPC run: the interval runner driving :class:`MPCAgent`."""

    def __init__(self, cfg: MPCConfig) -> None:
        cfg.validate()
        # one thread before the networks are built: their orthogonal initialisation
        # differs in the last bits under a multi-threaded BLAS (measured: a run built
        # first in a fresh process differed from later ones in approx_kl's 6th digit)
        torch.set_num_threads(1)
        agent = AdaptiveAgent(cfg) if cfg.method == "adaptive" else MPCAgent(cfg)
        super().__init__(cfg, agent, {"mpc": cfg})


# Options ftc.experiments passes to every method's controller that configure
# PPO only (ftc.controller): accepted and ignored here, so that one experiment
# can compare PPO and MPC. Only the documented ones; anything else is an error.
#   --pretrain       ftc.experiments --pretrain
#   --offline-steps  the example in ftc.experiments --controller-args --help
#   --update-every   scripts/bench_experiments.py --reduced (with --offline-steps)
IGNORED_CONTROLLER_OPTIONS: dict[str, dict[str, Any]] = {
    "--pretrain": {"action": "store_const", "const": True},
    "--offline-steps": {"type": int, "metavar": "N"},
    "--update-every": {"type": int, "metavar": "N"},
}


def build_parser() -> argparse.ArgumentParser:
    """The command line: one option per MPCConfig field, plus the ignored PPO options."""
    parser = OneLineParser(
        prog="python -m ftc.mpc", allow_abbrev=False,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=mpc_agent.__doc__.split("\n\n")[0],
        epilog=mpc_agent.__doc__.split("\n\n", 1)[1])
    add_run_options(parser, MPCConfig)
    ignored = parser.add_argument_group(
        "accepted and ignored",
        "PPO options of ftc.controller that ftc.experiments passes to every method\n"
        "(its --pretrain, --controller-args); they do not apply to MPC: a note, no effect")
    for flag, spec in IGNORED_CONTROLLER_OPTIONS.items():
        ignored.add_argument(flag, dest="ignored_" + flag[2:].replace("-", "_"), default=None,
                             help="ignored (ftc.controller: see its --help)", **spec)
    return parser


def parse_args(argv: Sequence[str] | None = None) -> MPCConfig:
    """The run's config from the command line; bad input exits 2 before anything is written."""
    parser = build_parser()
    ns = vars(parser.parse_args(argv))  # unknown options: exit 2 naming them
    given = {}
    for flag in IGNORED_CONTROLLER_OPTIONS:
        value = ns.pop("ignored_" + flag[2:].replace("-", "_"))
        if value is not None:
            given[flag] = value
    cfg = config_from_namespace(MPCConfig, ns)
    check_or_exit(parser, cfg)
    if given:
        shown = " ".join(k if v is True else f"{k} {v}" for k, v in given.items())
        print(f"{parser.prog}: note: ignoring {shown} (ftc.controller's PPO options)",
              file=sys.stderr)
    return cfg


def main(argv: Sequence[str] | None = None) -> int:
    cfg = parse_args(argv)
    torch.set_num_threads(1)

    def run() -> None:
        run_cfg = cfg
        if cfg.resume:
            run_cfg = read_run_configs(cfg.resume, {"mpc": MPCConfig})["mpc"]
            run_cfg.resume = run_cfg.out = cfg.resume
            for k in ("lcm_url", "prefix", "attach", "allow_network", "quiet", "tensorboard"):
                setattr(run_cfg, k, getattr(cfg, k))
        MPCController(run_cfg).run()

    return run_or_report(TOOL, run, out=cfg.resume or cfg.out)


if __name__ == "__main__":
    sys.exit(main())
