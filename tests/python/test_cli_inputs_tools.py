"""Every option of ftc.experiments, ftc.simulate, ftc.replay, ftc.relay,
ftc.export and ./build/plant with bad values: exit 2, one line on stderr
naming the flag, no traceback, nothing written (Reliability item 2; the
controller and the MPC are walked by test_cli_inputs.py).

The Python options are walked from the parsers themselves (an option added
later is walked too) and parsed in process: each tool's ``parse_args`` does
every check its ``main`` does before starting anything. The plant's options
are walked from its --help, each case a short subprocess on a private LCM URL
(ttl=0) and prefix. Values tried: 0, -1, nan, inf, 1e18, the empty string and
a word. The values that are valid input for an option are listed in ACCEPTED
(each reviewed by hand); for them the test asserts that parsing succeeds (the
plant: that it starts and answers), and still that nothing is written.
"""

from __future__ import annotations

import argparse
import io
import re
import signal
import subprocess
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import pytest

from ftc.common.build_info import plant_binary
from ftc.experiments import cli as experiments_cli
from ftc.plant import LcmPlant, PlantGoneError, private_lcm_url, private_prefix
from ftc.tools import export, relay, replay, simulate

BAD_VALUES = ["0", "-1", "nan", "inf", "1e18", "", "abc"]
NAMES = {"0", "-1", "nan", "inf", "1e18", "abc"}  # every bad value but '' is a valid name
# (tool, option) -> the values of BAD_VALUES that are valid input, reviewed one by one
ACCEPTED: dict[tuple[str, str], set[str]] = {
    ("ftc.experiments", "--out"): NAMES,             # a directory name (relative to the cwd)
    ("ftc.experiments", "--seeds"): {"0"},
    ("ftc.experiments", "--scenario-seed"): {"0"},
    ("ftc.experiments", "--run-timeout"): {"0"},     # 0: no timeout
    ("ftc.experiments", "--controller-args"): {""},  # no extra arguments
    ("ftc.experiments", "--tensorboard"): NAMES,     # a directory name (relative to the cwd)
    ("ftc.export", "--out"): NAMES,                  # an .onnx file name (relative to the cwd)
    ("ftc.export", "--weights"): NAMES,              # the node's weights file name
    ("ftc.export", "--verify-states"): {"0"},        # 0: no onnxruntime check
    ("ftc.simulate", "--seed"): {"0"},
    ("ftc.simulate", "--out"): NAMES,                # a CSV file name
    ("ftc.replay", "--channel"): NAMES,              # a channel name (not in the log: a run-time error)
    ("ftc.replay", "--episode"): {"0"},
    ("ftc.replay", "--figure"): NAMES,               # no suffix: PNG
    ("ftc.replay", "--csv"): NAMES,
    ("ftc.relay", "--client-prefix"): NAMES,         # any non-empty prefix other than the plant's
    ("ftc.relay", "--plant-prefix"): NAMES,
    ("ftc.relay", "--loss"): {"0"},
    ("ftc.relay", "--duplicate"): {"0"},
    ("ftc.relay", "--seed"): {"0"},
    ("plant", "--prefix"): NAMES,
    ("plant", "--seed"): {"0"},
    ("plant", "--start-step"): {"0"},
}


def _base(tool: str, tmp_path: Path) -> list[str]:
    """The arguments every case of ``tool`` starts with (valid on their own)."""
    log = tmp_path / "x.lcmlog"  # never read: parse_args checks only the options
    return {"ftc.experiments": ["single", "--out", str(tmp_path / "out")],
            "ftc.simulate": ["--out", str(tmp_path / "traj.csv")],
            "ftc.replay": [str(log)],
            "ftc.relay": ["--client-prefix", "CLIENT_", "--plant-prefix", "PLANT_"],
            # never read either: the checkpoint is opened only when the export runs
            "ftc.export": [str(tmp_path / "checkpoint.pt"), "--out", str(tmp_path / "p.onnx")],
            }[tool]


TOOLS = {"ftc.experiments": experiments_cli, "ftc.simulate": simulate, "ftc.replay": replay,
         "ftc.relay": relay, "ftc.export": export}


def _value_options(parser: argparse.ArgumentParser) -> list[str]:
    return [a.option_strings[0] for a in parser._actions  # noqa: SLF001 - the parser's own
            if a.option_strings and a.nargs != 0 and a.dest != "help"]


CASES = [(tool, flag, value) for tool, module in TOOLS.items()
         for flag in _value_options(module.build_parser()) for value in BAD_VALUES]


def test_every_option_is_walked():
    walked = {(t, f) for t, f, _ in CASES}
    assert len(walked) == 13 + 6 + 4 + 6 + 3, sorted(walked)
    for tool, flag in ACCEPTED:
        assert tool == "plant" or (tool, flag) in walked, (tool, flag)


@pytest.mark.parametrize("tool,flag,value", CASES, ids=[f"{t}{f}={v!r}" for t, f, v in CASES])
def test_bad_value_exits_2_with_one_line_naming_the_flag(tool, flag, value, tmp_path,
                                                         monkeypatch):
    work = tmp_path / "cwd"  # relative names resolve here; it must stay empty
    work.mkdir()
    monkeypatch.chdir(work)
    argv = [*_base(tool, tmp_path), flag, value]
    err = io.StringIO()
    with redirect_stderr(err), redirect_stdout(io.StringIO()):
        try:
            TOOLS[tool].parse_args(argv)
            code = 0
        except SystemExit as e:
            code = e.code
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cwd"], "something was written"
    assert list(work.iterdir()) == [], "something was written"
    if value in ACCEPTED.get((tool, flag), ()):
        assert code == 0, err.getvalue()
        return
    lines = err.getvalue().strip().splitlines()
    assert code == 2, f"exit {code}: {err.getvalue()}"
    assert len(lines) == 1, err.getvalue()
    assert "Traceback" not in err.getvalue()
    assert flag in lines[0], lines[0]


# ---------------------------------------------------------------------------
# ./build/plant
# ---------------------------------------------------------------------------

def _plant_options() -> list[str]:
    text = subprocess.run([str(plant_binary()), "--help"], capture_output=True, text=True,
                          timeout=10).stdout
    flags = re.findall(r"^\s+(?:-\w,)?(--[\w-]+) [A-Z]+", text, re.M)  # options with a value
    return flags


PLANT_CASES = [(flag, value) for flag in _plant_options() for value in BAD_VALUES]


def test_every_plant_option_is_walked():
    assert {f for f, _ in PLANT_CASES} == {
        "--scenario", "--lcm-url", "--prefix", "--seed", "--mode", "--rate", "--watchdog",
        "--safe-state", "--steps-per-interval", "--start-step", "--session-timeout", "--key-file"}


@pytest.mark.parametrize("flag,value", PLANT_CASES, ids=[f"plant{f}={v!r}" for f, v in PLANT_CASES])
def test_plant_bad_value_exits_2_with_one_line_naming_the_flag(flag, value, tmp_path):
    url, prefix = private_lcm_url(), private_prefix()
    base = [] if flag == "--lcm-url" else ["--lcm-url", url]
    base += [] if flag == "--prefix" else ["--prefix", prefix]
    stderr = tmp_path / "stderr"
    with open(stderr, "wb") as err:
        proc = subprocess.Popen([str(plant_binary()), *base, flag, value], cwd=tmp_path,
                                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err)
    try:
        if value in ACCEPTED.get(("plant", flag), ()):
            # Accepted: it starts and answers (the HELLO handshake), then stops on SIGINT.
            try:
                link = LcmPlant(url, value if flag == "--prefix" else prefix, process=proc)
            except PlantGoneError as e:
                pytest.fail(f"the plant did not answer: {e}: {stderr.read_text()}")
            proc.send_signal(signal.SIGINT)
            assert proc.wait(timeout=10) == 0
            link.close()
            return
        code = proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    text = stderr.read_text()
    lines = text.strip().splitlines()
    assert code == 2, f"exit {code}: {text}"
    assert len(lines) == 1 and lines[0].startswith("plant: error: "), text
    assert flag in lines[0], lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["stderr"], "something was written"
