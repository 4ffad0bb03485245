"""Every option of the run command lines with bad values: exit 2, one line on
stderr naming the flag, no traceback, nothing written (Reliability item 2).

The options are walked from the parsers themselves, so an option added later
is walked too. Values tried on each option that takes one: 0, -1, nan, inf,
1e18, the empty string and a word. A few of them are valid for some options
(seed 0, a zero coefficient, an unbounded KL target); those are listed in
ACCEPTED, and for them the test asserts only that parsing succeeds.
"""

from __future__ import annotations

import argparse
import io
from contextlib import redirect_stderr
from pathlib import Path

import pytest

from ftc.common.cli import NONZERO, needs
from ftc.control import registry
from ftc.tools import controller as controller_cli
from ftc.tools import mpc as mpc_cli

BAD_VALUES = ["0", "-1", "nan", "inf", "1e18", "", "abc"]
# (option, value) pairs that are valid input (each reviewed by hand)
ACCEPTED = {
    ("--seed", "0"), ("--pretrain-ent-coef", "0"), ("--ppo-ent-coef", "0"),
    ("--ppo-vf-coef", "0"), ("--ppo-gamma", "0"), ("--ppo-gae-lambda", "0"),
    ("--pretrain-open-fraction", "0"), ("--cem-smoothing", "0"), ("--ppo-target-kl", "1e18"),
    ("--branch-fraction", "0"), ("--teacher-rounds", "0"), ("--teacher-refits", "0"),
    ("--identify-every", "0"), ("--identify-trigger", "0"), ("--teacher-stop-loss", "0"),
    ("--band", "0"),  # balance: act on any imbalance
    ("--learn-terminal-band", "0"),  # learned-mpc: end episodes at the estimated demand
    ("--fine-tune-margin", "0"),  # adaptive-policy: every setting rated better is a label
    ("--teacher-memory", "0"), ("--teacher-check-every", "0"), ("--teacher-check-regret", "0"),
    # 0: that part switched off
    ("--scenario", ""),                       # the nominal plant
    ("--prefix", "0"), ("--prefix", "-1"), ("--prefix", "nan"), ("--prefix", "inf"),
    ("--prefix", "1e18"), ("--prefix", "abc"),  # any non-empty channel prefix
    ("--push-policy", "0"), ("--push-policy", "-1"), ("--push-policy", "nan"),
    ("--push-policy", "inf"), ("--push-policy", "1e18"), ("--push-policy", "abc"),
    ("--pretrain-cache", ""), ("--pretrain-cache", "0"), ("--pretrain-cache", "-1"),
    ("--pretrain-cache", "nan"), ("--pretrain-cache", "inf"), ("--pretrain-cache", "1e18"),
    ("--pretrain-cache", "abc"),              # a cache directory ('' disables it)
    ("--tensorboard", "0"), ("--tensorboard", "-1"), ("--tensorboard", "nan"),
    ("--tensorboard", "inf"), ("--tensorboard", "1e18"),
    ("--tensorboard", "abc"),                 # a directory name (relative to the cwd)
    ("--checkpoint", ""),                     # adaptive-policy: the cached checkpoint
    ("--adaptive-cache", "0"), ("--adaptive-cache", "-1"), ("--adaptive-cache", "nan"),
    ("--adaptive-cache", "inf"), ("--adaptive-cache", "1e18"),
    ("--adaptive-cache", "abc"),              # a cache directory
}
# --out is given a fresh directory by every case (its checks: test_fault_injection.py)
SKIPPED = {"--out"}



def _acting(tool: str, flag: str) -> list[str]:
    """The method and the options under which ``flag`` acts: the first method of
    the tool whose command line offers it, and what its NEEDS ask for (an option
    given where it has no effect is refused before its value is checked)."""
    name = OFFERED[(tool, flag)]
    if name is None:
        return []
    m = registry.method(name)
    need = needs(m.config_class()).get(flag[2:].replace("-", "_"))
    dep, value = (need[0] if isinstance(need, list) else need) if need else (None, None)
    if dep is None or dep in m.options or value is NONZERO:  # NONZERO: met by the default
        return ["--method", name]
    return ["--method", name, f"--{dep.replace('_', '-')}", *([] if value is True else [value])]


SINGLE = Path(__file__).resolve().parents[2] / "scenarios" / "single.toml"
TOOLS = {"ftc.controller": controller_cli, "ftc.mpc": mpc_cli}


def _value_options(parser: argparse.ArgumentParser) -> list[str]:
    flags = []
    for action in parser._actions:  # noqa: SLF001 - walking the parser's own options
        if not action.option_strings or action.nargs == 0 or action.dest == "help":
            continue
        if isinstance(action, argparse.BooleanOptionalAction):
            continue
        flags.append(action.option_strings[0])
    return flags


# every option of every method's command line, with the first method that offers it
OFFERED: dict[tuple[str, str], str | None] = {}
for _tool, _module in TOOLS.items():
    for _name in registry.tool_methods(_tool):
        for _flag in _value_options(_module.build_parser(_name)):
            OFFERED.setdefault((_tool, _flag), None if _flag == "--method" else _name)
CASES = [(tool, flag, value) for (tool, flag) in OFFERED if flag not in SKIPPED
         for value in BAD_VALUES]


def test_every_option_is_walked():
    assert len({(t, f) for t, f, _ in CASES}) >= 60  # the controller's 50-odd and the MPC's


@pytest.mark.parametrize("tool,flag,value", CASES, ids=[f"{t}{f}={v!r}" for t, f, v in CASES])
def test_bad_value_exits_2_with_one_line_naming_the_flag(tool, flag, value, tmp_path):
    out = tmp_path / "out"
    base = [] if flag == "--scenario" else ["--scenario", str(SINGLE)]
    err = io.StringIO()
    with redirect_stderr(err):
        try:
            TOOLS[tool].parse_args([*base, *_acting(tool, flag), flag, value, "--out", str(out)])
            code = 0
        except SystemExit as e:
            code = e.code
    assert not out.exists() and list(tmp_path.iterdir()) == [], "something was written"
    if (flag, value) in ACCEPTED or (flag == "--scenario" and value == ""):
        assert code == 0, err.getvalue()
        return
    lines = err.getvalue().strip().splitlines()
    assert code == 2, f"exit {code}: {err.getvalue()}"
    assert len(lines) == 1, err.getvalue()
    assert "Traceback" not in err.getvalue()
    # the line names the option (argparse's own messages name it as "argument --x")
    assert flag in lines[0] or flag.lstrip("-") in lines[0], lines[0]


def test_the_base_class_names_only_its_own_run_local_fields():
    """RUN_LOCAL_FIELDS names RunConfig's fields; a subclass marks its own
    (metadata run_local), and every config gets the same set as before they
    were marked, so checkpoints' configuration stamps are unchanged."""
    from dataclasses import fields

    from ftc.control.run.config import RUN_LOCAL_FIELDS, RunConfig, run_local_fields
    from ftc.control.agents.learned.guided_ppo import GuidedConfig
    from ftc.control.agents.mpc_config import MPCConfig
    from ftc.control.agents.physics.mpc import ModelMPCConfig
    from ftc.control.agents.ppo import ControllerConfig

    assert set(RUN_LOCAL_FIELDS) <= {f.name for f in fields(RunConfig)}
    own = set(RUN_LOCAL_FIELDS)
    assert run_local_fields(RunConfig()) == own
    for cls in (ControllerConfig, GuidedConfig):
        assert run_local_fields(cls()) == own | {"pretrain_cache", "push_policy", "push_url",
                                                 "push_key_file"}
    assert run_local_fields(MPCConfig()) == own
    assert run_local_fields(ModelMPCConfig()) == own | {"pretrain_cache"}
