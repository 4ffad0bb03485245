"""``python -m ftc.plugin``: a controller from outside the package on the
interval runner, scored as every method is.

    python -m ftc.plugin --agent examples.custom_agent:make_agent --out runs/mine
    python -m ftc.plugin --agent mypackage.agents:make_agent --scenario scenarios/single.toml
    python -m ftc.plugin --agent sb3:runs/sb3/model.zip --out runs/sb3
    python -m ftc.plugin --agent onnx:policy.onnx --out runs/onnx

``ftc.controller --method SPEC`` and ``ftc.mpc --method SPEC`` run the same
(:mod:`ftc.control.plugins` lists the specs). The run writes what every run
writes (config.json with the spec, metrics.csv, checkpoint.pt, done.json);
--resume continues it (a plug-in agent's state is what its state_dict
returns). A spec that gives no controller is exit 2 with one line naming the
module, attribute or file.
"""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

from ftc.common.cli import OneLineParser, config_from_namespace
from ftc.control.cli import add_run_options, check_or_exit, resume_configs, run_or_report
from ftc.control.plugins import (PluginConfig, PluginError, guard_actions, is_plugin,
                                 load_agent)
from ftc.control.runner import IntervalRunner

TOOL = "ftc.plugin"


class PluginController(IntervalRunner):
    """A plug-in run: the interval runner driving the agent its spec names."""

    tool = TOOL

    def __init__(self, cfg: PluginConfig, agent) -> None:
        super().__init__(cfg, guard_actions(agent, cfg.agent), {"plugin": cfg})


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog=f"python -m {TOOL}", allow_abbrev=False,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1])
    add_run_options(parser, PluginConfig)
    return parser


def parse_args(argv: Sequence[str] | None = None) -> tuple[PluginConfig, object]:
    """(the run's config, its agent); bad input exits 2 before anything is written."""
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    cfg = config_from_namespace(PluginConfig, vars(parser.parse_args(argv)))
    if not cfg.resume and not cfg.agent:
        parser.error("--agent is required (module.path:factory, sb3:PATH.zip or "
                     "onnx:PATH.onnx)")
    check_or_exit(parser, cfg)
    if cfg.resume:
        cfg = resume_configs(parser, argv, {"plugin": (cfg, "")}, {"plugin": PluginConfig},
                             lambda stored, named: None)["plugin"]
    try:
        agent = load_agent(cfg.agent, cfg)
    except PluginError as e:
        parser.error(f"--agent: {e}")
    return cfg, agent


def plugin_argv(argv: Sequence[str] | None) -> list[str] | None:
    """``argv`` of ftc.controller or ftc.mpc with ``--method SPEC`` as ftc.plugin
    reads it (``--agent SPEC``), or None where --method names no plug-in."""
    argv = list(sys.argv[1:] if argv is None else argv)
    for i, word in enumerate(argv):
        if word == "--method" and i + 1 < len(argv) and is_plugin(argv[i + 1]):
            return [*argv[:i], "--agent", *argv[i + 1:]]
        if word.startswith("--method=") and is_plugin(word.split("=", 1)[1]):
            return [*argv[:i], "--agent=" + word.split("=", 1)[1], *argv[i + 1:]]
    return None


def main(argv: Sequence[str] | None = None) -> int:
    import torch

    torch.set_num_threads(1)
    cfg, agent = parse_args(argv)
    return run_or_report(TOOL, lambda: PluginController(cfg, agent).run(),
                         out=cfg.resume or cfg.out)


if __name__ == "__main__":
    sys.exit(main())
