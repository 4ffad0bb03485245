"""``python -m ftc.mpc``: the MPC controllers of :mod:`ftc.control.registry`
on the interval runner (see :mod:`ftc.control.agents.physics.mpc` for what they do)."""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

import torch

from ftc.common.cli import OneLineParser, config_from_namespace, given_options
from ftc.control import registry
from ftc.control.agents.physics import mpc as mpc_agent
from ftc.tools import plugin as plugin_cli
from ftc.tools.run_cli import (add_run_options, check_or_exit, method_argv, refuse_ignored,
                             resume_configs, run_or_report)
from ftc.control.agents.mpc_config import MPCConfig
from ftc.control.run.runner import IntervalRunner

TOOL = "ftc.mpc"


class MPCController(IntervalRunner):
    """An MPC run: the interval runner driving the agent of ``cfg.method``."""

    tool = TOOL

    def __init__(self, cfg: MPCConfig) -> None:
        cfg.validate()
        # one thread before the networks are built: their orthogonal initialisation
        # differs in the last bits under a multi-threaded BLAS (measured: a run built
        # first in a fresh process differed from later ones in approx_kl's 6th digit)
        torch.set_num_threads(1)
        super().__init__(cfg, registry.agent_for({"mpc": cfg}, cfg.method), {"mpc": cfg})


def build_parser() -> argparse.ArgumentParser:
    """The command line: one option per MPCConfig field."""
    parser = OneLineParser(
        prog="python -m ftc.mpc", allow_abbrev=False,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=mpc_agent.__doc__.split("\n\n")[0],
        epilog=mpc_agent.__doc__.split("\n\n", 1)[1])
    add_run_options(parser, MPCConfig)
    return parser


def parse_args(argv: Sequence[str] | None = None) -> MPCConfig:
    """The run's config from the command line (with --resume, the run's own,
    every option given honoured or refused); bad input exits 2 before anything
    is written."""
    parser = build_parser()
    argv = method_argv(parser, argv, TOOL)  # former names of the methods: warned, mapped
    ns = vars(parser.parse_args(argv))  # unknown options: exit 2 naming them
    cfg = config_from_namespace(MPCConfig, ns)
    check_or_exit(parser, cfg)
    if cfg.resume:
        return resume_configs(parser, argv, {"mpc": (cfg, "")}, {"mpc": MPCConfig},
                              lambda stored, named: refuse_ignored(parser, stored["mpc"], named)
                              )["mpc"]
    refuse_ignored(parser, cfg, given_options(parser, argv))
    return cfg


def main(argv: Sequence[str] | None = None) -> int:
    plugin = plugin_cli.plugin_run(argv, TOOL)  # --method [NAME=]SPEC, or --resume of one
    if plugin is not None:
        return plugin
    cfg = parse_args(argv)
    torch.set_num_threads(1)
    return run_or_report(TOOL, lambda: MPCController(cfg).run(), out=cfg.resume or cfg.out)


if __name__ == "__main__":
    sys.exit(main())
