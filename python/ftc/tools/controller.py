"""The paper's controller (Algorithm 1, method ppo-offline): PPO online on the
real plant, offline on a world model refitted from real experience, interval
by interval; and the other methods of ftc.control.registry it runs, each
with its own options.

    python -m ftc.controller --scenario scenarios/single.toml --seed 0 --out runs/s0
    python -m ftc.controller --method ppo-online --out runs/online  # ppo, offline phase off
    python -m ftc.controller --method ppo-robust --help             # ppo-robust's options
    python -m ftc.controller --method closed --out runs/closed      # a baseline
    python -m ftc.controller --resume runs/s0                       # continue a stopped run
    python -m ftc.controller --resume runs/s0 --intervals 20        # extend a run to 20

Outputs in --out DIR: config.json (resolved config, seed, git revision),
metrics.csv (one row per interval, rewritten atomically after each), a
checkpoint after every interval (checkpoint.pt, torch.load(weights_only=True)),
done.json when the run has finished; plant.pid while a launched plant runs;
run.lock while the run writes (pid, start time, host): a second writer is
refused, a lock whose holder is gone is taken over with a note. An --out that
already holds a run is refused (--resume continues it, --overwrite replaces
it: the old run is deleted only once the new one has saved an interval). On
--resume, an option that fixes results (scenario, seed, method, sizes) may be
given only with the run's own value; --intervals beyond the run's extends it,
exactly as if it had been asked for from the start.
With --tensorboard DIR, TensorBoard scalars in DIR: every PPO update's
statistics, every interval's metrics, reward terms and steps/s
(docs/ecosystem.md). A PPO run's policy exports to ONNX with
python -m ftc.export OUT --out policy.onnx (OUT: the run's --out).

Failures (one line on stderr, "ftc.controller: error: ..."; nothing written
after the last finished interval, so metrics.csv and checkpoint.pt stay those
of that interval and --resume continues from it):

    exit 2  bad input: a flag, a scenario file, an --out that holds a run or is
            in use, or a --resume directory whose config.json or checkpoint.pt is
            corrupt, truncated or from another configuration
    exit 3  the plant stopped answering (retried with back-off for
            --link-give-up-timeout seconds): "plant gone at interval K, step T: ..."
    exit 4  a non-finite number: observation, PPO loss, gradient or weights
    exit 5  a result could not be written (disk full, unwritable file)

SIGINT, SIGTERM or SIGHUP stops the run as a failure does (the plant shut
down, no partial file, --resume continues): "ftc.controller: stopped by
SIGTERM; ...", exit 130, 143 or 129.
"""

from __future__ import annotations

import argparse
import sys
import textwrap
from typing import Any, Sequence

import torch

from ftc.control import registry
from ftc.control.agents.ppo import ControllerConfig
from ftc.control.run.agent import Agent
from ftc.control.run.runner import IntervalRunner
from ftc.learning.ppo import PPOConfig
from ftc.learning.ppo_policy import ENGINE_ALIASES, ENGINES
from ftc.tools import plugin as plugin_cli
from ftc.tools.run_cli import (method_parser, parse_method_args, read_run_configs,
                                run_or_report, stored_config)

TOOL = "ftc.controller"
DEFAULT = "ppo"
CHOICES = {"ppo": {"engine": (*ENGINES, *ENGINE_ALIASES)}}


def run_configs(cfg: Any, ppo_config: PPOConfig | None = None) -> dict[str, Any]:
    """The config parts of a run of ``cfg.method``: its run config and the parts
    its agent has (a PPO method's hyperparameters: ``ppo_config``, or the defaults)."""
    parts = registry.method(cfg.method).agent_class().parts
    return {"controller": cfg, **{name: (ppo_config if name == "ppo" and ppo_config is not None
                                         else part()) for name, (part, _) in parts.items()}}


def make_agent(cfg: Any, ppo_config: PPOConfig | None = None) -> Agent:
    """The agent of --method, as :mod:`ftc.control.registry` lists it."""
    return registry.agent_for(run_configs(cfg, ppo_config), cfg.method)


class Controller(IntervalRunner):
    """A controller run: the interval runner driving the agent of ``cfg.method``."""

    tool = TOOL

    def __init__(self, cfg: Any, ppo_config: PPOConfig | None = None) -> None:
        cfg.validate()
        # one thread before the networks are built: their orthogonal initialisation
        # differs in the last bits under a multi-threaded BLAS (measured: a run built
        # first in a fresh process differed from later ones in approx_kl's 6th digit)
        torch.set_num_threads(1)
        configs = run_configs(cfg, ppo_config)
        super().__init__(cfg, registry.agent_for(configs, cfg.method), configs)

    @property
    def ppo(self):
        """The PPO algorithm of a PPO run (None for a baseline)."""
        return getattr(self.agent, "ppo", None)


def _texts() -> tuple[str, str]:
    """The command line's description and epilog."""
    return (textwrap.fill(" ".join(__doc__.split("\n\n")[0].split())
                          + " Prints one progress line per interval.", 79),
            __doc__.split("\n\n", 1)[1])


def build_parser(method: str = DEFAULT) -> argparse.ArgumentParser:
    """The command line of a run of ``method`` (what ``--method METHOD --help`` shows)."""
    return method_parser(TOOL, registry.method(method), *_texts(), CHOICES)


def parse_args(argv: Sequence[str] | None = None) -> tuple[Any, PPOConfig]:
    """The run's config and PPO hyperparameters (the defaults where the method
    has no policy) from the command line (with --resume, the run's own, every
    option given honoured or refused); bad input exits 2 before anything is
    written. ``--method NAME`` is read first: the options offered are NAME's."""
    configs = parse_method_args(TOOL, argv, DEFAULT, *_texts(), CHOICES)
    return configs["controller"], configs.get("ppo", PPOConfig())


def resume_config(out: str) -> tuple[Any, PPOConfig]:
    """The configuration a stopped run was started with (from its config.json);
    raises CheckpointError when it is missing or malformed."""
    configs = read_run_configs(out, {"controller": stored_config(TOOL), "ppo": PPOConfig})
    cfg, ppo = configs["controller"], configs["ppo"]
    cfg.resume, cfg.out = out, out
    return cfg, ppo


__all__ = ["Controller", "ControllerConfig", "main", "make_agent", "parse_args", "resume_config"]


def main(argv: Sequence[str] | None = None) -> int:
    plugin = plugin_cli.plugin_run(argv, TOOL)  # --method [NAME=]SPEC, or --resume of one
    if plugin is not None:
        return plugin
    torch.set_num_threads(1)
    cfg, ppo = parse_args(argv)
    return run_or_report(TOOL, lambda: Controller(cfg, ppo).run(), out=cfg.resume or cfg.out)


if __name__ == "__main__":
    sys.exit(main())
