"""``python -m ftc.mpc``: the MPC controllers of :mod:`ftc.control.registry`
on the interval runner, each with its own options (see
:mod:`ftc.control.agents.physics.mpc` for what they do)."""

from __future__ import annotations

import argparse
import sys
from typing import Any, Sequence

import torch

from ftc.control import registry
from ftc.control.agents.physics import mpc as mpc_agent
from ftc.control.run.runner import IntervalRunner
from ftc.tools import plugin as plugin_cli
from ftc.tools.run_cli import method_parser, parse_method_args, run_or_report

TOOL = "ftc.mpc"
DEFAULT = "oracle-mpc"


class MPCController(IntervalRunner):
    """An MPC run: the interval runner driving the agent of ``cfg.method``."""

    tool = TOOL

    def __init__(self, cfg: Any) -> None:
        cfg.validate()
        # one thread before the networks are built: their orthogonal initialisation
        # differs in the last bits under a multi-threaded BLAS (measured: a run built
        # first in a fresh process differed from later ones in approx_kl's 6th digit)
        torch.set_num_threads(1)
        super().__init__(cfg, registry.agent_for({"mpc": cfg}, cfg.method), {"mpc": cfg})


def _texts() -> tuple[str, str]:
    """The command line's description and epilog."""
    return mpc_agent.__doc__.split("\n\n")[0], mpc_agent.__doc__.split("\n\n", 1)[1]


def build_parser(method: str = DEFAULT) -> argparse.ArgumentParser:
    """The command line of a run of ``method`` (what ``--method METHOD --help`` shows)."""
    return method_parser(TOOL, registry.method(method), *_texts())


def parse_args(argv: Sequence[str] | None = None) -> Any:
    """The run's config from the command line (with --resume, the run's own,
    every option given honoured or refused); bad input exits 2 before anything
    is written. ``--method NAME`` is read first: the options offered are NAME's."""
    return parse_method_args(TOOL, argv, DEFAULT, *_texts())["mpc"]


def main(argv: Sequence[str] | None = None) -> int:
    plugin = plugin_cli.plugin_run(argv, TOOL)  # --method [NAME=]SPEC, or --resume of one
    if plugin is not None:
        return plugin
    cfg = parse_args(argv)
    torch.set_num_threads(1)
    return run_or_report(TOOL, lambda: MPCController(cfg).run(), out=cfg.resume or cfg.out)


if __name__ == "__main__":
    sys.exit(main())
