"""The adaptive controller (the paper's Algorithm 1): PPO online on the real plant,
offline on a world model refitted from real experience, interval by interval.

    python -m ftc.controller --scenario scenarios/single.toml --seed 0 --out runs/s0
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
from dataclasses import fields
from typing import Sequence

import torch

from ftc.common.cli import (OneLineParser, add_dataclass_options, config_from_namespace, flag,
                            given_options)
from ftc.control.agent import Agent
from ftc.control.balance import BalanceAgent
from ftc.control.baselines import BaselineAgent
from ftc.control.cli import (add_run_options, check_or_exit, read_run_configs, resume_configs,
                             run_or_report)
from ftc.control.config import RunConfig
from ftc.control.ppo_agent import PPO_METHODS, ControllerConfig, PPOAgent
from ftc.control.ppo_robust_agent import RobustPPOAgent
from ftc.control.runner import IntervalRunner
from ftc.learning.ppo import PPOConfig
from ftc.learning.ppo_policy import ENGINE_ALIASES, ENGINES

TOOL = "ftc.controller"


def make_agent(cfg: ControllerConfig, ppo_config: PPOConfig) -> Agent:
    """The agent of --method: PPO (Algorithm 1) or a baseline."""
    if cfg.method == "ppo":
        return PPOAgent(cfg, ppo_config)
    if cfg.method == "balance":
        return BalanceAgent()
    if cfg.method == "ppo-robust":
        return RobustPPOAgent(cfg, ppo_config)
    return BaselineAgent(cfg.method, cfg.seed)


class Controller(IntervalRunner):
    """A controller run: the interval runner driving the agent of ``cfg.method``."""

    tool = TOOL

    def __init__(self, cfg: ControllerConfig, ppo_config: PPOConfig) -> None:
        cfg.validate()
        # one thread before the networks are built: their orthogonal initialisation
        # differs in the last bits under a multi-threaded BLAS (measured: a run built
        # first in a fresh process differed from later ones in approx_kl's 6th digit)
        torch.set_num_threads(1)
        super().__init__(cfg, make_agent(cfg, ppo_config),
                         {"controller": cfg, "ppo": ppo_config})

    @property
    def ppo(self):
        """The PPO algorithm of a ``--method ppo`` run (None for a baseline)."""
        return getattr(self.agent, "ppo", None)


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="python -m ftc.controller", allow_abbrev=False,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=textwrap.fill(" ".join(__doc__.split("\n\n")[0].split())
                                  + " Prints one progress line per interval.", 79),
        epilog=__doc__.split("\n\n", 1)[1])
    add_run_options(parser, ControllerConfig)
    add_dataclass_options(parser.add_argument_group("PPO hyperparameters"), PPOConfig, "ppo-",
                          choices={"engine": (*ENGINES, *ENGINE_ALIASES)})
    return parser


def parse_args(argv: Sequence[str] | None = None) -> tuple[ControllerConfig, PPOConfig]:
    """The run's configs from the command line (with --resume, the run's own,
    every option given honoured or refused); bad input exits 2 before anything
    is written."""
    parser = build_parser()
    ns = vars(parser.parse_args(argv))
    cfg = config_from_namespace(ControllerConfig, ns)
    ppo = config_from_namespace(PPOConfig, ns, "ppo-")
    check_or_exit(parser, cfg, {"ppo-": ppo})
    if cfg.resume:
        def no_ppo_options_for_a_baseline(stored: dict, named: set[str]) -> None:
            if stored["controller"].method not in PPO_METHODS:
                _refuse_ppo_options(parser, named, stored["controller"].method)

        configs = resume_configs(parser, argv, {"controller": (cfg, ""), "ppo": (ppo, "ppo-")},
                                 {"controller": ControllerConfig, "ppo": PPOConfig},
                                 no_ppo_options_for_a_baseline)
        return configs["controller"], configs["ppo"]
    if cfg.method not in PPO_METHODS:
        _refuse_ppo_options(parser, given_options(parser, argv), cfg.method)
    return cfg, ppo


def _refuse_ppo_options(parser: argparse.ArgumentParser, named: set[str], method: str) -> None:
    """A baseline has no policy: an option that configures PPO would have no effect."""
    run = {f.name for f in fields(RunConfig)}
    ppo_only = [flag(f.name) for f in fields(ControllerConfig)
                if f.name not in run and f.name != "method" and f.name in named]
    ppo_only += [flag(f.name, "ppo-") for f in fields(PPOConfig) if "ppo_" + f.name in named]
    if ppo_only:
        parser.error(f"{ppo_only[0]} has no effect with --method {method} (it configures the "
                     f"PPO methods: {', '.join(PPO_METHODS)})")


def resume_config(out: str) -> tuple[ControllerConfig, PPOConfig]:
    """The configuration a stopped run was started with (from its config.json);
    raises CheckpointError when it is missing or malformed."""
    configs = read_run_configs(out, {"controller": ControllerConfig, "ppo": PPOConfig})
    cfg, ppo = configs["controller"], configs["ppo"]
    cfg.resume, cfg.out = out, out
    return cfg, ppo


def main(argv: Sequence[str] | None = None) -> int:
    torch.set_num_threads(1)
    cfg, ppo = parse_args(argv)
    return run_or_report(TOOL, lambda: Controller(cfg, ppo).run(), out=cfg.resume or cfg.out)


if __name__ == "__main__":
    sys.exit(main())
