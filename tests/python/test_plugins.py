"""Plug-in controllers: a user's Agent (examples/custom_agent.py), an SB3 model
trained by examples/sb3_ppo.py and a policy exported by ftc.export, each scored
by the benchmark on real plant processes over LCM and in process, under the name
given; a bad spec is one line and exit 2 naming what is wrong, nothing written;
a benchmark of plug-ins resumes."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ftc.tools import plugin as plugin_cli

from ftc.control.agents import plugins
from ftc.experiments import methods

REPO = Path(__file__).resolve().parents[2]
SHORT = ["--scenarios", str(REPO / "scenarios" / "single.toml"), "--seeds", "0",
         "--intervals", "2", "--steps-per-interval", "64", "--reference", "oracle-mpc",
         "--jobs", "2"]


def _benchmark(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO / "python"),
                                                      os.environ.get("PYTHONPATH", "")]))
    return subprocess.run([sys.executable, "-m", "ftc.experiments", "benchmark", *args],
                          cwd=cwd, env=env, capture_output=True, text=True, timeout=600)


def _rows(out: Path) -> list[dict]:
    with open(out / "results.csv", newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture(scope="module")
def policies(tmp_path_factory) -> dict[str, Path]:
    """An SB3 model from examples/sb3_ppo.py (one short rollout) and an ONNX policy
    that ftc.export wrote from a short PPO run of ftc.controller."""
    root = tmp_path_factory.mktemp("policies")
    env = dict(os.environ, OMP_NUM_THREADS="1",
               PYTHONPATH=os.pathsep.join([str(REPO / "python"), os.environ.get("PYTHONPATH", "")]))
    sb3 = subprocess.run([sys.executable, str(REPO / "examples" / "sb3_ppo.py"), "--steps",
                          "512", "--out", str(root / "sb3.zip")], cwd=root, env=env,
                         capture_output=True, text=True, timeout=600)
    assert sb3.returncode == 0, sb3.stderr[-2000:]
    run = subprocess.run([sys.executable, "-m", "ftc.controller", "--intervals", "1",
                          "--steps-per-interval", "128", "--update-every", "64", "--no-offline",
                          "--link", "core", "--quiet", "--out", str(root / "ppo")], cwd=REPO,
                         env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    export = subprocess.run([sys.executable, "-m", "ftc.export", str(root / "ppo"), "--out",
                             str(root / "policy.onnx")], cwd=REPO, env=env,
                            capture_output=True, text=True, timeout=600)
    assert export.returncode == 0, export.stderr[-2000:]
    return {"sb3": root / "sb3.zip", "onnx": root / "policy.onnx"}


@pytest.mark.parametrize("link", ["lcm", "core"])
def test_the_three_kinds_score_on_the_benchmark(policies, tmp_path, link):
    out = tmp_path / "bench"
    proc = _benchmark(*SHORT, "--link", link, "--out", str(out), "--methods",
                      "mine=examples.custom_agent:make_agent", f"sb3:{policies['sb3']}",
                      f"exported=onnx:{policies['onnx']}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = _rows(out)
    names = {r["method"] for r in rows}
    assert {"mine", "sb3", "exported", "oracle-mpc", "closed"} == names
    for name in ("mine", "sb3", "exported"):
        mine = [r for r in rows if r["method"] == name]
        assert len(mine) == 2 and all(float(r["reward_per_step"]) > 0 for r in mine)
        assert all(r["normalized_score"] != "" for r in mine if r["interval"] == "1")
    # the custom agent is the example's rule: closed until the wings differ, so in the
    # healthy interval 0 it earns exactly what all-closed earns
    closed0 = next(r for r in rows if r["method"] == "closed" and r["interval"] == "0")
    mine0 = next(r for r in rows if r["method"] == "mine" and r["interval"] == "0")
    assert mine0["reward_per_step"] == closed0["reward_per_step"]
    meta = json.loads((out / "benchmark.json").read_text())
    assert meta["methods"]["exported"]["args"] == ["--agent", f"onnx:{policies['onnx']}"]


@pytest.mark.slow  # 10-30 s: the fresh-clone CI stays under its 10 minutes
def test_a_benchmark_of_plugins_resumes(tmp_path):
    out = tmp_path / "bench"
    assert _benchmark(*SHORT, "--link", "core", "--out", str(out), "--methods",
                      "mine=examples.custom_agent:make_agent").returncode == 0
    (out / "results.csv").unlink()
    run = out / "runs" / "single" / "t00" / "mine" / "s0" / "result.json"
    run.unlink()  # the plug-in's run unfinished: --resume redoes it
    proc = _benchmark("--resume", "--out", str(out), "--jobs", "1")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert run.is_file() and {r["method"] for r in _rows(out)} >= {"mine"}


@pytest.mark.parametrize("spec, message", [
    ("x=nosuchmodule:make", "cannot import module 'nosuchmodule'"),
    ("x=examples.custom_agent:nothing", "module 'examples.custom_agent' has no callable "
                                        "'nothing'"),
    ("x=examples.custom_agent:OuterTransfer.act", "has no callable"),
    ("x=sb3:/nonexistent/model.zip", "sb3:/nonexistent/model.zip: no such file"),
    (f"x=onnx:{REPO / 'README.md'}", "not a readable ONNX model"),
    ("closed=examples.custom_agent:make_agent", "closed is a built-in method"),
    ("a b=examples.custom_agent:make_agent", "may hold letters, digits"),
])
def test_a_bad_spec_is_one_line_exit_2_and_nothing_written(spec, message, tmp_path):
    out = tmp_path / "bench"
    proc = _benchmark(*SHORT, "--out", str(out), "--methods", spec)
    assert proc.returncode == 2 and message in proc.stderr, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert not out.exists()


def test_a_policy_that_answers_no_valves_is_refused(tmp_path):
    with pytest.raises(plugins.PluginError, match="holds values other than 0 and 1"):
        plugins._checked(lambda levels: np.full(6, 0.5), "onnx:x.onnx")
    with pytest.raises(plugins.PluginError, match="fails on full tanks"):
        plugins._checked(lambda levels: 1 / 0, "onnx:x.onnx")


def test_specs_names_and_the_tools_method_option():
    assert plugins.default_name("examples.custom_agent:make_agent") == "make_agent"
    assert plugins.default_name("sb3:runs/x/My Model.zip") == "My-Model"
    assert plugins.default_name("onnx:/a/policy.onnx") == "policy"
    assert plugins.split_name("mine=examples.custom_agent:make_agent") == (
        "mine", "examples.custom_agent:make_agent")
    assert plugins.split_name("sb3:runs/a=b/model.zip") == (None, "sb3:runs/a=b/model.zip")
    assert plugin_cli.plugin_run(["--method", "balance"], "ftc.controller") is None
    assert methods.resolve_methods(["balance", "closed"], None) == ["balance", "closed"]


def test_ftc_controller_runs_a_plugin_as_its_method(tmp_path):
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "ftc.controller", "--method",
                           "examples.custom_agent:make_agent", "--intervals", "1",
                           "--steps-per-interval", "32", "--link", "core", "--out", str(out)],
                          cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    config = json.loads((out / "config.json").read_text())
    assert config["plugin"]["agent"] == "examples.custom_agent:make_agent"
    assert (out / "done.json").is_file()


TINY = ["--intervals", "1", "--steps-per-interval", "16", "--link", "core", "--quiet"]


@pytest.mark.parametrize("tool,option", [("controller", "--method"), ("mpc", "--method"),
                                         ("plugin", "--agent")])
def test_name_equals_spec_runs_as_the_readme_writes_it(tool, option, tmp_path, capsys):
    """Issue 35, item 7: ``--method NAME=SPEC`` (``--agent`` on ftc.plugin) runs the
    plug-in under NAME; a spec that gives no controller names the option given."""
    import importlib

    main = importlib.import_module(f"ftc.tools.{tool}").main
    out = tmp_path / "run"
    assert main([option, "mine=examples.custom_agent:make_agent", *TINY, "--out", str(out)]) == 0
    assert json.loads((out / "config.json").read_text())["plugin"]["agent"] == \
        "mine=examples.custom_agent:make_agent"
    assert (out / "done.json").is_file()
    with pytest.raises(SystemExit) as e:
        main([option, "mine=no_such_module_here:f", *TINY, "--out", str(tmp_path / "bad")])
    assert e.value.code == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert line.startswith(f"ftc.{tool}: error: {option}: cannot import module "
                           "'no_such_module_here'"), line
    assert not (tmp_path / "bad").exists()


@pytest.mark.parametrize("tool", ["controller", "mpc"])
def test_a_plugin_run_started_by_a_tool_resumes_there(tool, tmp_path):
    """Issue 35, item 9: ``ftc.controller --resume DIR`` of the plug-in run it
    started continues it (it said: malformed run configuration, KeyError 'controller')."""
    import importlib

    main = importlib.import_module(f"ftc.tools.{tool}").main
    out = tmp_path / "run"
    assert main(["--method", "examples.custom_agent:make_agent", *TINY, "--out", str(out)]) == 0
    assert main(["--resume", str(out), "--intervals", "2", "--quiet"]) == 0
    rows = list(csv.DictReader(open(out / "metrics.csv")))
    assert [r["interval"] for r in rows] == ["0", "1"]
    assert json.loads((out / "done.json").read_text())["intervals"] == 2


def test_a_factory_gets_the_config_only_where_it_has_a_parameter_to_fill(tmp_path):
    cfg = plugins.PluginConfig(agent="x:y", scenario=None)
    module = tmp_path / "factories_for_test.py"
    module.write_text(
        "from ftc.control.run.agent import Agent\n"
        "class A(Agent):\n"
        "    def __init__(self, margin=0.15):\n"
        "        self.margin = margin\n"
        "    def act(self, obs, ctx):\n"
        "        return [0] * 6\n"
        "def with_cfg(cfg):\n"
        "    a = A()\n"
        "    a.seed = cfg.seed\n"
        "    return a\n")
    sys.path.insert(0, str(tmp_path))
    try:
        assert plugins.load_agent("factories_for_test:A", cfg).margin == 0.15  # A(), not A(cfg)
        assert plugins.load_agent("factories_for_test:with_cfg", cfg).seed == cfg.seed
    finally:
        sys.path.remove(str(tmp_path))


def test_sb3_learn_fine_tunes_the_model_on_the_plant_and_checkpoints_it(policies, tmp_path):
    import torch
    from stable_baselines3 import PPO

    out = tmp_path / "learn"
    proc = subprocess.run([sys.executable, "-m", "ftc.controller", "--method",
                           f"sb3:{policies['sb3']}", "--sb3-learn", "--intervals", "1",
                           "--steps-per-interval", "512", "--link", "core", "--quiet",
                           "--out", str(out)], cwd=REPO, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    model = PPO.load(str(policies["sb3"]), device="cpu")
    rows = list(csv.DictReader(open(out / "metrics.csv")))
    # the example's n_steps (256) plant steps per update: two in a 512-step interval
    assert model.n_steps == 256 and rows[0]["sb3_updates"] == "2"
    trained = torch.load(out / "checkpoint.pt", weights_only=True)["agent"]["policy"]
    before = model.policy.state_dict()
    assert trained.keys() == before.keys()
    assert any(not torch.equal(trained[k], before[k]) for k in before)  # it learned
    # without the flag the model only acts, and the flag is refused for other kinds
    fixed = subprocess.run([sys.executable, "-m", "ftc.controller", "--method",
                            f"onnx:{policies['onnx']}", "--sb3-learn", "--out",
                            str(tmp_path / "no")], cwd=REPO, capture_output=True, text=True,
                           timeout=300)
    assert fixed.returncode == 2
    assert "--sb3-learn fine-tunes an sb3:PATH.zip model" in fixed.stderr
    assert not (tmp_path / "no").exists()


def test_a_benchmark_gives_sb3_learn_to_its_sb3_methods_only(policies, tmp_path):
    out = tmp_path / "bench"
    proc = _benchmark("--scenarios", str(REPO / "scenarios" / "single.toml"), "--seeds", "0",
                      "--intervals", "1", "--steps-per-interval", "256", "--link", "core",
                      "--jobs", "2", "--reference", "oracle-mpc", "--methods",
                      f"tuned=sb3:{policies['sb3']}", f"exported=onnx:{policies['onnx']}",
                      "--controller-args=--sb3-learn", "--out", str(out))
    assert proc.returncode == 0, proc.stderr[-2000:]
    runs = {p.parents[2].name: json.loads(p.read_text())["plugin"]
            for p in out.glob("runs/single/t00/*/s0/controller/config.json")
            if p.parents[2].name in ("tuned", "exported")}
    assert runs["tuned"]["sb3_learn"] is True and runs["exported"]["sb3_learn"] is False
    metrics = (out / "runs" / "single" / "t00" / "tuned" / "s0" / "controller" /
               "metrics.csv").read_text()
    assert "sb3_updates" in metrics.splitlines()[0]
    # with no sb3: method the option acts on nothing: refused before any run
    proc = _benchmark(*SHORT, "--methods", f"exported=onnx:{policies['onnx']}",
                      "--controller-args=--sb3-learn", "--out", str(tmp_path / "none"))
    assert proc.returncode == 2 and "--sb3-learn" in proc.stderr
