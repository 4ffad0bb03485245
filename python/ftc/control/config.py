"""The options every run shares (scenario, seed, output, intervals, the plant
link), declared once, and opening the plant link they describe. The
controller's and the MPC's configs extend :class:`RunConfig`."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from ftc.common.cli import Check, at_least, positive
from ftc.common.constants import DEFAULT_LCM_URL, DEFAULT_PREFIX
from ftc.common.errors import PlantLostError, RunError, UsageError
from ftc.plant.lcm_link import LcmPlant, LinkConfig, check_loopback_url, launch
from ftc.plant.link import CorePlant, PlantError, PlantGoneError, PlantLink
from ftc.plant.realtime_link import RealtimeLink
from ftc.plant.signing import load_key

LINKS = ("lcm", "core")
MAX_INTERVALS = 10_000
MAX_STEPS_PER_INTERVAL = 10_000_000


@dataclass
class RunConfig:
    """Options of every interval run (the controller's and the MPC's)."""

    scenario: str | None = field(default="single", metadata={"help": (
        "fault scenario given to the plant: a packaged one's name (single, "
        "multiple, nominal, abrupt) or a TOML file (empty string: nominal plant)")})
    seed: int = field(default=0, metadata={"check": at_least(0, 2**31 - 1), "help": (
        "seeds the policy, the world model, model rollouts and the random baseline")})
    out: str = field(default="runs/controller", metadata={"help": "output directory"})
    intervals: int = field(default=10, metadata={"check": at_least(1, MAX_INTERVALS),
                                                 "help": "number of intervals (paper: 10)"})
    steps_per_interval: int = field(default=512, metadata={
        "check": at_least(1, MAX_STEPS_PER_INTERVAL), "help": (
            "t_online: real steps per interval; forwarded to the plant so its degradation "
            "interval matches (paper: 512)")})
    link: str = field(default="lcm", metadata={"choices": LINKS, "help": (
        "lcm: the real plant process over LCM (launched, or --attach); core: the same "
        "physics in this process (fast experiments)")})
    attach: bool = field(default=False, metadata={"help": (
        "drive a plant already running (./build/plant) on --lcm-url/--prefix instead "
        "of launching one")})
    lcm_url: str | None = field(default=None, metadata={"help": (
        "LCM URL of the plant; must stay on this machine (memq://, or udpm:// with ttl=0) "
        "unless --allow-network (None: a private loopback port when launching; "
        f"{DEFAULT_LCM_URL} with --attach)")})
    realtime: float | None = field(default=None, metadata={"check": positive(10_000.0), "help": (
        "launch the plant in real-time mode at this many steps per second and control it "
        "as it runs: it does not wait for the controller, learning runs off the control "
        "loop, and metrics.csv gains the deadline columns (docs/deploy.md). With --attach "
        "a plant in real-time mode is recognised by itself (None: lockstep)")})
    watchdog: float = field(default=1.0, metadata={"check": positive(3600.0), "help": (
        "with --realtime: seconds without a valid command after which the plant puts the "
        "valves in the safe state (all closed)")})
    allow_network: bool = field(default=False, metadata={"help": (
        "accept an --lcm-url whose traffic may leave this machine (ttl != 0, tcpq://); "
        "with --attach only, as launched plants are kept on loopback")})
    key_file: str | None = field(default=None, metadata={"help": (
        "with --attach: sign and check every message with the bus key in this file (hex, "
        "mode 600; the plant's --key-file). A launched plant gets a fresh key per run "
        "(docs/deploy.md)")})
    prefix: str | None = field(default=None, metadata={"help": (
        f"LCM channel prefix (None: a private one when launching; {DEFAULT_PREFIX} with "
        "--attach)")})
    resume: str | None = field(default=None, metadata={"help": (
        "continue the stopped run in this directory from its last checkpoint; with "
        "--intervals N beyond the run's, extend it (more control and learning); the "
        "options that fix its results may be given only with the run's own values")})
    overwrite: bool = field(default=False, metadata={"help": (
        "replace the run already in --out: it is moved aside when this run starts and "
        "deleted once this run's first interval is saved (moved back if this run fails "
        "before)")})
    link_retry_timeout: float = field(default=0.05, metadata={"check": positive(60.0), "help": (
        "seconds before an unanswered plant message is re-sent (LCM on loopback answers "
        "in well under 1 ms; a lost message costs this much)")})
    link_backoff: float = field(default=2.0, metadata={"check": Check(low=1.0, high=100.0),
                                                       "help": (
        "the re-send wait grows by this factor after each unanswered re-send of one message")})
    link_give_up_timeout: float = field(default=5.0, metadata={"check": positive(3600.0),
                                                               "help": (
        "seconds without an answer after which the plant counts as gone (exit 3)")})
    quiet: bool = field(default=False, metadata={"help": "no progress lines on the console"})
    tensorboard: str | None = field(default=None, metadata={"help": (
        "write TensorBoard scalars into this directory: every PPO update's statistics, "
        "every interval's metrics.csv columns, reward terms and steps/s "
        "(docs/ecosystem.md; None: none)")})

    def validate(self) -> None:
        """Cross-field rules (single fields declare their own constraints);
        raises ValueError naming the flag."""
        if not self.out.strip():
            raise ValueError("--out must name a directory, got ''")
        if self.resume is not None and not self.resume.strip():
            raise ValueError("--resume must name a run directory, got ''")
        if self.resume is not None and self.overwrite:
            raise ValueError("--overwrite replaces a run, --resume continues it: give one")
        if self.tensorboard is not None and not self.tensorboard.strip():
            raise ValueError("--tensorboard must name a directory, got ''")
        if self.realtime is not None and (self.link != "lcm" or self.attach):
            raise ValueError("--realtime launches a real-time plant process: it needs --link lcm "
                             "and no --attach (an attached plant's own mode is used)")
        if self.prefix is not None and not self.prefix.strip():
            raise ValueError("--prefix must not be empty (None: a private one)")
        if self.key_file is not None and not (self.attach and self.link == "lcm"):
            raise ValueError("--key-file is for --attach (a launched plant gets a fresh key)")
        if not self.link_retry_timeout <= self.link_give_up_timeout:
            raise ValueError("--link-retry-timeout must be > 0 and <= --link-give-up-timeout")
        if self.lcm_url is not None and self.link == "lcm":
            try:
                check_loopback_url(self.lcm_url)
            except ValueError as e:
                if not self.allow_network:
                    raise ValueError(f"--lcm-url: {e}") from None
                if not self.attach:
                    # ftc.plant.launch keeps the plants it starts on loopback
                    raise ValueError(f"--lcm-url {self.lcm_url}: --allow-network works with "
                                     "--attach only (launched plants stay on ttl=0)") from None

    def link_config(self) -> LinkConfig:
        return LinkConfig(retry_timeout=self.link_retry_timeout,
                          give_up_timeout=self.link_give_up_timeout, backoff=self.link_backoff)


# RunConfig's fields that do not change a run's results: a checkpoint written
# under other values of these may be resumed (everything else must match), and
# a resumed run takes them from its own command line. A subclass or another
# config part marks its own such fields with metadata {"run_local": True}.
RUN_LOCAL_FIELDS = ("out", "resume", "overwrite", "lcm_url", "prefix", "attach", "allow_network",
                    "key_file",
                    "realtime", "watchdog", "quiet", "link_retry_timeout", "link_backoff",
                    "link_give_up_timeout", "tensorboard")


def run_local_fields(cfg: Any) -> frozenset[str]:
    """The fields of config dataclass ``cfg`` that do not change results
    (:data:`RUN_LOCAL_FIELDS` and those whose metadata says ``run_local``)."""
    return frozenset(f.name for f in dataclasses.fields(cfg)
                     if f.name in RUN_LOCAL_FIELDS or f.metadata.get("run_local"))
# Fields a resumed run may raise: more intervals extend it.
EXTENSIBLE_FIELDS = ("intervals",)
# The files that make a run directory hold a run (what --overwrite replaces).
RUN_FILES = ("config.json", "metrics.csv", "checkpoint.pt", "done.json")


def open_plant(cfg: RunConfig, start_step: int) -> PlantLink:
    """The plant a run drives, at ``start_step`` operating steps (resume).

    Raises PlantLostError when it does not answer, UsageError when it refuses
    its input (a malformed scenario), RunError otherwise."""
    scenario = cfg.scenario or None
    try:
        if cfg.link == "core":
            return CorePlant(scenario, cfg.seed, steps_per_interval=cfg.steps_per_interval,
                             start_step=start_step)
        if cfg.attach:
            url, prefix = cfg.lcm_url or DEFAULT_LCM_URL, cfg.prefix or DEFAULT_PREFIX
            try:
                key = load_key(cfg.key_file) if cfg.key_file else None
            except ValueError as e:
                raise UsageError(f"--key-file {e}") from None
            link = LcmPlant(url, prefix, config=cfg.link_config(), allow_network=cfg.allow_network,
                            key=key)
            if link.last_state.rate_hz > 0:  # real time: the run STARTs it at its own age
                link.close()
                return RealtimeLink(url, prefix, config=cfg.link_config(),
                                    allow_network=cfg.allow_network, key=key)
            at = link.hello().operating_steps
            if at != start_step:
                link.close()
                raise UsageError(f"attached plant is at operating step {at}, the run needs "
                                 f"{start_step}: start it with --start-step {start_step}")
            return link
        extra = ["--steps-per-interval", str(cfg.steps_per_interval)]
        if start_step:
            extra += ["--start-step", str(start_step)]
        if cfg.realtime is not None:
            extra += ["--mode", "realtime", "--rate", repr(cfg.realtime),
                      "--watchdog", repr(cfg.watchdog)]
        # a fresh key per run: a process without it changes nothing (docs/deploy.md)
        return launch(scenario, cfg.seed, lcm_url=cfg.lcm_url, prefix=cfg.prefix,
                      extra_args=extra, config=cfg.link_config(),
                      link_class=RealtimeLink if cfg.realtime is not None else None, sign=True)
    except PlantGoneError as e:
        raise PlantLostError(f"plant gone before the first step: {e}") from None
    except PlantError as e:  # refused to start; its exit code 2 means bad input
        raise (UsageError if e.exit_code == 2 else RunError)(str(e)) from None
