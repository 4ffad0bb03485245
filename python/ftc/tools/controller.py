"""The paper's controller (Algorithm 1, method ppo-offline): PPO online on the
real plant, offline on a world model refitted from real experience, interval
by interval; and the other methods of ftc.control.registry it runs.

    python -m ftc.controller --scenario scenarios/single.toml --seed 0 --out runs/s0
    python -m ftc.controller --method ppo-online --out runs/online  # = --method ppo --no-offline
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
from typing import Any, Sequence

import torch

from ftc.common.cli import (OneLineParser, add_dataclass_options, config_from_namespace, flag,
                            given_options)
from ftc.control import registry
from ftc.tools import plugin as plugin_cli
from ftc.control.run.agent import Agent
from ftc.tools.run_cli import (add_run_options, check_or_exit, method_argv, read_run_configs,
                             refuse_ignored, resume_configs, run_or_report)
from ftc.control.run.config import RunConfig
from ftc.control.agents.ppo import PPO_METHODS, ControllerConfig
from ftc.control.agents.learned.guided_ppo import GUIDED_FIELDS as ROBUST_FIELDS, GuidedConfig as RobustConfig
from ftc.control.run.runner import IntervalRunner
from ftc.learning.ppo import PPOConfig
from ftc.learning.ppo_policy import ENGINE_ALIASES, ENGINES

TOOL = "ftc.controller"


def make_agent(cfg: ControllerConfig, ppo_config: PPOConfig) -> Agent:
    """The agent of --method, as :mod:`ftc.control.registry` lists it."""
    return registry.agent_for({"controller": cfg, "ppo": ppo_config}, cfg.method)


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
        """The PPO algorithm of a PPO run (None for a baseline)."""
        return getattr(self.agent, "ppo", None)


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="python -m ftc.controller", allow_abbrev=False,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=textwrap.fill(" ".join(__doc__.split("\n\n")[0].split())
                                  + " Prints one progress line per interval.", 79),
        epilog=__doc__.split("\n\n", 1)[1])
    add_run_options(parser, RobustConfig)  # every method's options; each refuses the others'
    add_dataclass_options(parser.add_argument_group("PPO hyperparameters"), PPOConfig, "ppo-",
                          choices={"engine": (*ENGINES, *ENGINE_ALIASES)})
    return parser


def controller_config(values: dict[str, Any]) -> ControllerConfig:
    """The config of a run of ``values["method"]`` (its registry config class)
    from option values, the options of other methods dropped (they have no
    effect on it and are refused when given); TypeError for an option no
    method has."""
    unknown = sorted(values.keys() - {f.name for f in fields(RobustConfig)})
    if unknown:  # no method has it: not a config this controller wrote
        raise TypeError(f"unknown options {', '.join(unknown)}")
    cls = registry.method(values.get("method", "ppo")).config_class()
    own = {f.name for f in fields(cls)}
    return cls(**{k: v for k, v in values.items() if k in own})


# a stored run's fields the controller no longer offers (cli.read_run_configs)
controller_config.RETIRED_FIELDS = ControllerConfig.RETIRED_FIELDS  # type: ignore[attr-defined]


def parse_args(argv: Sequence[str] | None = None) -> tuple[ControllerConfig, PPOConfig]:
    """The run's configs from the command line (with --resume, the run's own,
    every option given honoured or refused); bad input exits 2 before anything
    is written. ``--method NAME`` takes every name of the registry this tool
    runs (ppo-offline: ppo --offline) and, with a warning, its former names."""
    parser = build_parser()
    argv = method_argv(parser, argv, TOOL)
    ns = vars(parser.parse_args(argv))
    every = config_from_namespace(RobustConfig, ns)  # this command line, every option
    ppo = config_from_namespace(PPOConfig, ns, "ppo-")
    check_or_exit(parser, every, {"ppo-": ppo})
    named = given_options(parser, argv)
    if every.resume:
        def no_effect(stored: dict, named: set[str]) -> None:
            _refuse_no_effect(parser, named, stored["controller"])

        configs = resume_configs(parser, argv, {"controller": (every, ""), "ppo": (ppo, "ppo-")},
                                 {"controller": controller_config, "ppo": PPOConfig}, no_effect)
        return configs["controller"], configs["ppo"]
    cfg = controller_config(vars(every))
    _refuse_no_effect(parser, named, cfg)
    return cfg, ppo


def _refuse_no_effect(parser: argparse.ArgumentParser, named: set[str],
                      cfg: ControllerConfig) -> None:
    """Exit 2 on an option given that cannot act on a run of ``cfg``: a
    baseline has no policy (every PPO option), plain PPO no guided fit (the
    robust options), a run without --pretrain no pretraining."""
    method = cfg.method
    if method not in PPO_METHODS:
        run = {f.name for f in fields(RunConfig)}
        ppo_only = [flag(f.name) for f in fields(RobustConfig)
                    if f.name not in run and f.name != "method" and f.name in named]
        ppo_only += [flag(f.name, "ppo-") for f in fields(PPOConfig) if "ppo_" + f.name in named]
        if ppo_only:
            parser.error(f"{ppo_only[0]} has no effect with --method {method} (it configures "
                         f"the PPO methods: {', '.join(PPO_METHODS)})")
    robust = [flag(name) for name in ROBUST_FIELDS if name in named]
    if method not in registry.guided_methods() and robust:
        parser.error(f"{robust[0]} has no effect with --method {method} (it configures "
                     f"{', '.join(registry.guided_methods())})")
    refuse_ignored(parser, cfg, named)


def resume_config(out: str) -> tuple[ControllerConfig, PPOConfig]:
    """The configuration a stopped run was started with (from its config.json);
    raises CheckpointError when it is missing or malformed."""
    configs = read_run_configs(out, {"controller": controller_config, "ppo": PPOConfig})
    cfg, ppo = configs["controller"], configs["ppo"]
    cfg.resume, cfg.out = out, out
    return cfg, ppo


def main(argv: Sequence[str] | None = None) -> int:
    plugin = plugin_cli.plugin_run(argv, TOOL)  # --method [NAME=]SPEC, or --resume of one
    if plugin is not None:
        return plugin
    torch.set_num_threads(1)
    cfg, ppo = parse_args(argv)
    return run_or_report(TOOL, lambda: Controller(cfg, ppo).run(), out=cfg.resume or cfg.out)


if __name__ == "__main__":
    sys.exit(main())
