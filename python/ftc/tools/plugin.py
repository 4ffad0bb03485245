"""``python -m ftc.plugin``: a controller from outside the package on the
interval runner, scored as every method is.

    python -m ftc.plugin --agent examples.custom_agent:make_agent --out runs/mine
    python -m ftc.plugin --agent mine=mypackage.agents:make_agent --scenario scenarios/single.toml
    python -m ftc.plugin --agent sb3:runs/sb3/model.zip --out runs/sb3
    python -m ftc.plugin --agent onnx:policy.onnx --out runs/onnx

``ftc.controller --method [NAME=]SPEC`` and ``ftc.mpc --method [NAME=]SPEC``
run the same (:mod:`ftc.control.agents.plugins` lists the specs; NAME, the
name the agent goes by, defaults to the factory's name or the file's stem).
The run writes what every run writes (config.json with the spec, metrics.csv,
checkpoint.pt, done.json); --resume continues it, from this tool or from the
one that started it (a plug-in agent's state is what its state_dict returns).
A spec that gives no controller is exit 2 with one line naming the option,
and the module, attribute or file.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Sequence

from ftc.common.cli import OneLineParser, config_from_namespace
from ftc.control.agents.plugins import (PluginConfig, PluginError, guard_actions, is_plugin,
                                        load_agent)
from ftc.control.run.runner import IntervalRunner
from ftc.tools.run_cli import add_run_options, check_or_exit, resume_configs, run_or_report

TOOL = "ftc.plugin"


class PluginController(IntervalRunner):
    """A plug-in run: the interval runner driving the agent its spec names."""

    tool = TOOL

    def __init__(self, cfg: PluginConfig, agent, tool: str = TOOL) -> None:
        self.tool = tool
        super().__init__(cfg, guard_actions(agent, cfg.agent), {"plugin": cfg})


def build_parser(tool: str = TOOL, option: str = "--agent") -> argparse.ArgumentParser:
    """The command line of a plug-in run of ``tool``, the spec given as ``option``
    (``--agent`` here, ``--method`` on ftc.controller and ftc.mpc)."""
    parser = OneLineParser(
        prog=f"python -m {tool}", allow_abbrev=False,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1])
    if option != "--agent":
        parser.add_argument(option, dest="agent", default="", help=(
            "the plug-in: [NAME=]SPEC, SPEC one of module.path:factory, sb3:PATH.zip, "
            "onnx:PATH.onnx"))
    add_run_options(parser, PluginConfig, skip=() if option == "--agent" else ("agent",))
    return parser


def parse_args(argv: Sequence[str] | None = None, tool: str = TOOL, option: str = "--agent"
               ) -> tuple[PluginConfig, object]:
    """(the run's config, its agent); bad input exits 2 before anything is
    written, the line naming ``option``, the option the spec came in."""
    parser = build_parser(tool, option)
    argv = list(sys.argv[1:] if argv is None else argv)
    cfg = config_from_namespace(PluginConfig, vars(parser.parse_args(argv)))
    if not cfg.resume and not cfg.agent:
        parser.error(f"{option} is required ([NAME=]SPEC, SPEC one of module.path:factory, "
                     "sb3:PATH.zip or onnx:PATH.onnx)")
    check_or_exit(parser, cfg)
    if cfg.resume:
        cfg = resume_configs(parser, argv, {"plugin": (cfg, "")}, {"plugin": PluginConfig},
                             lambda stored, named: None)["plugin"]
    try:
        agent = load_agent(cfg.agent, cfg)
    except PluginError as e:
        parser.error(f"{option}: {e}")
    return cfg, agent


def plugin_run(argv: Sequence[str] | None, tool: str) -> int | None:
    """For ftc.controller and ftc.mpc, whose --method is read first: the exit
    code of the plug-in run ``argv`` asks for (``--method [NAME=]SPEC``, or
    ``--resume DIR`` of a run a plug-in started), or None when it asks for none."""
    argv = list(sys.argv[1:] if argv is None else argv)
    first = argparse.ArgumentParser(add_help=False, allow_abbrev=False)
    first.add_argument("--method")
    first.add_argument("--resume")
    known, _ = first.parse_known_args(argv)
    if known.method is not None:
        plugin = is_plugin(known.method)
    else:
        plugin = known.resume is not None and _started_by_plugin(Path(known.resume))
    return main(argv, tool, "--method") if plugin else None


def _started_by_plugin(out: Path) -> bool:
    """Whether the run in ``out`` is a plug-in's (its config.json says; a missing
    or unreadable one is the tool's own error to report)."""
    try:
        doc = json.loads((out / "config.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(doc, dict) and isinstance(doc.get("plugin"), dict) \
        and "controller" not in doc and "mpc" not in doc


def main(argv: Sequence[str] | None = None, tool: str = TOOL, option: str = "--agent") -> int:
    import torch

    torch.set_num_threads(1)
    cfg, agent = parse_args(argv, tool, option)
    return run_or_report(tool, lambda: PluginController(cfg, agent, tool).run(),
                         out=cfg.resume or cfg.out)


if __name__ == "__main__":
    sys.exit(main())
