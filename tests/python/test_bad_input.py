"""Bad input gets one clear line, a non-zero exit code of the README's table
and nothing partial that misleads (issue 35, items 8, 10-13): a plug-in's
invalid action mid-run, an action outside the Gymnasium env's action space,
a finished run whose metrics.csv gained a row, the recovery advice after a run
killed before its first interval, an ONNX model of the wrong input width and
a bound printed in %g. Runs are in process on the C++ core (--link core),
16 steps per interval: each a fraction of a second."""

from __future__ import annotations

import csv
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ftc.common.errors import EXIT_FAILURE, EXIT_USAGE
from ftc.control import plugin_cli
from ftc.control.cli import run_or_report
from ftc.control.runner import replacement

REPO = Path(__file__).resolve().parents[2]
SHORT = ["--link", "core", "--intervals", "2", "--steps-per-interval", "16", "--quiet"]

# A plug-in whose act answers well until (interval, step) = AT, then with BAD[kind].
PLUGIN = '''
import numpy as np
from ftc.control.agent import Agent

AT = {at}
BAD = {{"short": [0] * 5, "nan": [np.nan] + [0] * 5, "two": [2] + [0] * 5,
        "minus": [-1] + [0] * 5, "half": [0.5] + [0] * 5, "raises": None}}


class Faulty(Agent):
    def __init__(self, kind):
        self.name, self.kind = "faulty", kind

    def act(self, obs, ctx):
        if (ctx.interval, ctx.step) == AT:
            if self.kind == "raises":
                raise ZeroDivisionError("division by zero\\nsecond line")
            return np.array(BAD[self.kind])
        return np.zeros(6)

''' + "\n".join(f"def {k}():\n    return Faulty({k!r})\n"
                for k in ("short", "nan", "two", "minus", "half", "raises", "good"))


@pytest.fixture
def plugin_module(tmp_path, monkeypatch):
    """A module of faulty plug-ins, importable under a name of this test's."""
    def make(at: tuple[int, int]) -> str:
        name = f"faulty_plugins_{abs(hash((str(tmp_path), at)))}"
        (tmp_path / f"{name}.py").write_text(PLUGIN.format(at=at))
        monkeypatch.syspath_prepend(str(tmp_path))
        return name
    return make


def _plugin(argv: list[str], capsys) -> tuple[int, list[str]]:
    code = plugin_cli.main(argv)
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    return code, err


@pytest.mark.parametrize("kind, code, says", [
    ("short", EXIT_USAGE, "of shape (5,), not (6,)"),
    ("nan", EXIT_USAGE, "holds values other than 0 and 1"),
    ("two", EXIT_USAGE, "[2, 0, 0, 0, 0, 0] holds values other than 0 and 1"),
    ("minus", EXIT_USAGE, "holds values other than 0 and 1"),
    ("half", EXIT_USAGE, "holds values other than 0 and 1"),
    ("raises", EXIT_FAILURE, "raised ZeroDivisionError: division by zero"),
])
def test_a_plugins_invalid_action_mid_run_is_one_line_naming_agent_interval_and_step(
        plugin_module, tmp_path, capsys, kind, code, says):
    module = plugin_module((1, 5))
    out = tmp_path / "run"
    got, err = _plugin(["--agent", f"{module}:{kind}", *SHORT, "--out", str(out)], capsys)
    assert got == code and len(err) == 1, err
    assert err[0].startswith(f"ftc.plugin: error: plug-in {module}:{kind} at interval 1, "
                             f"step 5"), err
    assert says in err[0], err
    # interval 0 finished and stays resumable; nothing of interval 1 was kept
    with open(out / "metrics.csv", newline="") as f:
        assert [r["interval"] for r in csv.DictReader(f)] == ["0"]


def test_a_plugin_failing_in_interval_0_leaves_no_run_behind(plugin_module, tmp_path, capsys):
    module = plugin_module((0, 3))
    out = tmp_path / "run"
    got, err = _plugin(["--agent", f"{module}:two", *SHORT, "--out", str(out)], capsys)
    assert got == EXIT_USAGE and len(err) == 1 and "at interval 0, step 3" in err[0], err
    assert not out.exists() or not any(out.iterdir()), list(out.iterdir())


def test_a_finished_run_resumed_with_a_stray_metrics_row_gets_its_checkpoints_rows_back(
        plugin_module, tmp_path, capsys):
    module = plugin_module((-1, -1))
    out = tmp_path / "run"
    assert _plugin(["--agent", f"{module}:good", *SHORT, "--out", str(out)], capsys)[0] == 0
    metrics = out / "metrics.csv"
    kept = metrics.read_text()
    metrics.write_text(kept + "2," + ",".join(["1"] * (kept.splitlines()[0].count(","))) + "\n")
    assert plugin_cli.main(["--resume", str(out), "--quiet"]) == 0
    said = capsys.readouterr().out
    assert "did not match the run's checkpoint (3 rows for 2 intervals)" in said, said
    assert metrics.read_text() == kept


def test_a_run_killed_before_its_first_interval_gets_advice_that_goes_on(
        plugin_module, tmp_path, capsys):
    """What SIGKILL leaves before interval 0 ends: config.json and no checkpoint;
    after an --overwrite, the replaced run in .replaced beside it. Both a plain
    rerun and --resume point to --overwrite, which then runs."""
    module = plugin_module((-1, -1))
    finished, out = tmp_path / "finished", tmp_path / "run"
    args = ["--agent", f"{module}:good", *SHORT]
    assert _plugin([*args, "--out", str(finished)], capsys)[0] == 0
    for case in ("fresh", "overwrite"):
        shutil.rmtree(out, ignore_errors=True)
        if case == "overwrite":  # the killed --overwrite moved the old run aside...
            shutil.copytree(finished, out)
            replacement(out).stash_old()
        out.mkdir(exist_ok=True)
        shutil.copy(finished / "config.json", out)  # ...and wrote its own config
        with pytest.raises(SystemExit) as plain:
            plugin_cli.main([*args, "--out", str(out)])
        assert plain.value.code == EXIT_USAGE
        err = capsys.readouterr().err
        assert "stopped before its first interval finished" in err and "--overwrite starts it " \
            "again" in err and "--resume" not in err, err
        assert plugin_cli.main(["--resume", str(out), "--quiet"]) == EXIT_USAGE
        err = capsys.readouterr().err
        assert "nothing to resume; start it again with --overwrite" in err, err
        assert _plugin([*args, "--out", str(out), "--overwrite"], capsys)[0] == 0
        assert (out / "done.json").is_file() and not (out / ".replaced").exists()


def test_a_real_sigkill_of_an_overwrite_before_its_first_interval_then_the_advice(
        plugin_module, tmp_path, capsys):
    """The state above made by a real SIGKILL: an --overwrite of a finished run,
    killed while its first (long) interval runs; --resume refuses, and the
    --overwrite it advises runs."""
    module = plugin_module((-1, -1))
    out = tmp_path / "run"
    args = ["--agent", f"{module}:good", "--link", "core", "--quiet"]
    assert _plugin([*args, "--intervals", "1", "--steps-per-interval", "16", "--out", str(out)],
                   capsys)[0] == 0
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(tmp_path), str(REPO / "python"), os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.Popen([sys.executable, "-m", "ftc.plugin", *args, "--intervals", "1",
                             "--steps-per-interval", "10000000", "--out", str(out),
                             "--overwrite"], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while not ((out / ".replaced").is_dir() and (out / "config.json").is_file()):
            assert proc.poll() is None and time.monotonic() < deadline, "never started"
            time.sleep(0.05)
        time.sleep(0.5)  # in its first interval
    finally:
        proc.kill()
        proc.wait()
    assert not (out / "checkpoint.pt").exists() and (out / ".replaced").is_dir()
    assert plugin_cli.main(["--resume", str(out), "--quiet"]) == EXIT_USAGE
    assert "start it again with --overwrite" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        plugin_cli.main([*args, "--intervals", "1", "--steps-per-interval", "16", "--out",
                         str(out)])
    err = capsys.readouterr().err
    assert "--overwrite starts it again" in err and "--resume" not in err, err
    assert _plugin([*args, "--intervals", "1", "--steps-per-interval", "16", "--out", str(out),
                    "--overwrite"], capsys)[0] == 0
    assert (out / "done.json").is_file() and not (out / ".replaced").exists()


def test_a_stop_inside_interval_0_does_not_offer_to_resume_an_empty_directory(tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()

    def stopped() -> None:
        raise KeyboardInterrupt

    assert run_or_report("ftc.controller", stopped, out=str(out)) == 130
    err = capsys.readouterr().err.strip()
    assert err == (f"ftc.controller: stopped by SIGINT; no interval had finished, so nothing "
                   f"was kept in {out} (run it again)"), err


@pytest.mark.parametrize("action", [
    np.full(6, 257.0), np.full(6, -255.0), np.array([np.nan] + [0.0] * 5),
    np.full(6, 0.99), np.array([1, 0, 1]), np.full(6, 2), np.array(["1"] * 6)])
def test_the_gym_env_refuses_actions_outside_its_action_space(action):
    import gymnasium as gym

    env = gym.make("ftc/FuelTransferCore-v0")
    try:
        obs, _ = env.reset(seed=0)
        assert not env.action_space.contains(action)
        with pytest.raises(ValueError, match=r"FuelTransferEnv.step: the action .* \(six valves, "
                                             r"each 0 or 1: MultiBinary\(6\)\)"):
            env.step(action)
        # nothing was applied: the plant steps on from where it was, as a fresh one does
        after, *_ = env.step(np.zeros(6))
        again, _ = env.reset(seed=0)
        fresh, *_ = env.step(np.zeros(6))
        np.testing.assert_array_equal(after, fresh)
        for ok in (np.ones(6), np.ones(6, dtype=bool), [1.0, 0.0, 1.0, 0.0, 1.0, 0.0]):
            env.step(ok)  # in the action space, whatever its dtype
    finally:
        env.close()


def test_an_onnx_model_of_the_wrong_input_width_is_one_line(tmp_path, capsys):
    onnx = pytest.importorskip("onnx")
    from onnx import TensorProto, helper

    graph = helper.make_graph(
        [helper.make_node("Identity", ["levels"], ["valves"])], "four",
        [helper.make_tensor_value_info("levels", TensorProto.FLOAT, ["N", 4])],
        [helper.make_tensor_value_info("valves", TensorProto.FLOAT, ["N", 4])])
    path = tmp_path / "four.onnx"
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), path)
    with pytest.raises(SystemExit) as exited:
        plugin_cli.main(["--agent", f"onnx:{path}", *SHORT, "--out", str(tmp_path / "run")])
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert exited.value.code == EXIT_USAGE and len(err) == 1, err
    assert f"onnx:{path}: input 'levels' has shape ['N', 4]; the policy takes the levels " \
           "[N, 6]" in err[0], err


def test_an_integer_bound_is_printed_as_an_integer(capsys):
    with pytest.raises(SystemExit):
        plugin_cli.main(["--agent", "m:f", "--seed", str(2**31), "--out", "unused"])
    err = capsys.readouterr().err
    assert f"must be <= {2**31 - 1}, got {2**31}" in err, err


if __name__ == "__main__":
    sys.exit(pytest.main([__file__]))
