"""The one registry of methods (ftc.control.registry): every method builds its
config and agent, one name means the same in ftc.controller, ftc.mpc and
ftc.experiments, former names warn and map, options that cannot act on a
method are refused, and an unknown method is named with the list of known ones."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import pytest

from ftc.control import registry

from ftc.tools import controller as controller_cli

from ftc.tools import mpc as mpc_cli
from ftc.control.run.agent import Agent
from ftc.tools.run_cli import read_run_configs
from ftc.control.run.metrics import metric_columns
from ftc.control.agents.mpc_config import MPCConfig
from ftc.control.agents.physics.ppo_robust import RobustConfig
from ftc.experiments.methods import METHODS as EXPERIMENT_METHODS
from ftc.learning.ppo import PPOConfig

NO_PLANT = ["--scenario", "", "--link", "core"]


def _configs(m: registry.Method, tmp_path) -> dict:
    argv = [*m.args, *NO_PLANT, "--out", str(tmp_path / m.name)]
    if m.tool == "ftc.controller":
        cfg, ppo = controller_cli.parse_args(argv)
        return {"controller": cfg, "ppo": ppo}
    return {"mpc": mpc_cli.parse_args(argv)}


@pytest.mark.parametrize("name", list(registry.METHODS))
def test_every_method_builds_its_config_and_agent(name, tmp_path):
    m = registry.METHODS[name]
    configs = _configs(m, tmp_path)
    cfg = next(iter(configs.values()))
    assert type(cfg) is m.config_class() and cfg.method == m.tool_method
    agent = registry.agent_for(configs, cfg.method)
    try:
        assert isinstance(agent, m.agent_class()) and isinstance(agent, Agent)
        assert set(m.columns) <= set(metric_columns(agent.extra_columns))
    finally:
        agent.close()
    assert m.knows in registry.KNOWS


def test_listing_the_methods_imports_no_torch():
    code = ("import sys; from ftc.control import registry; registry.METHODS; "
            "sys.exit('torch' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


@pytest.mark.parametrize("name", [n for n, m in registry.METHODS.items() if m.compared])
def test_one_name_means_the_same_in_every_tool(name, tmp_path):
    m = registry.METHODS[name]
    spec = EXPERIMENT_METHODS[name]
    assert spec.module == m.tool and spec.args[:2] == ("--method", name)
    assert (spec.label, spec.cost, spec.learns) == (m.label, m.cost, m.learns)
    # the tool given the registry's name runs what its own spelling runs
    spelled = registry.expand_method(["--method", name], m.tool)
    assert spelled == list(m.args)
    assert _configs(m, tmp_path) == _configs(
        registry.Method(m.name, m.label, m.tool, tuple(spelled), m.agent, m.config), tmp_path)


def test_ppo_offline_is_ppo_with_offline():
    a = controller_cli.parse_args(["--method", "ppo-offline", *NO_PLANT])
    b = controller_cli.parse_args(["--method", "ppo", "--offline", *NO_PLANT])
    assert a == b and a[0].method == "ppo" and a[0].offline
    c, _ = controller_cli.parse_args(["--method", "ppo-online", *NO_PLANT])
    assert not c.offline


@pytest.mark.parametrize("alias,name", sorted(registry.ALIASES.items()))
def test_a_former_name_warns_and_maps(alias, name, capsys):
    cfg = mpc_cli.parse_args(["--method", alias, *NO_PLANT])
    assert cfg.method == name
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"ftc.mpc: warning: --method {alias} is deprecated; use --method {name}"]
    assert registry.method(alias) is registry.METHODS[name]


@pytest.mark.parametrize("tool,argv,message", [
    (controller_cli, ["--method", "ppo", "--teacher-rounds", "1"],
     "--teacher-rounds has no effect with --method ppo (it configures ppo-robust, ppo-learned)"),
    (controller_cli, ["--method", "closed", "--offline-steps", "8"],
     "--offline-steps has no effect with --method closed"),
    (controller_cli, ["--method", "ppo-offline", "--pretrain-lr", "0.1"],
     "--pretrain-lr has no effect without --pretrain"),
    (controller_cli, ["--method", "ppo-online", "--offline"],
     "--offline is fixed by --method ppo-online"),
    (controller_cli, ["--method", "oracle-mpc"], "--method oracle-mpc is run by ftc.mpc"),
    (mpc_cli, ["--method", "oracle-mpc", "--cem-iterations", "2"],
     "--cem-iterations has no effect with --planner hold"),
    (mpc_cli, ["--method", "oracle-mpc", "--model-episodes", "2"],
     "--model-episodes has no effect with --method oracle-mpc (it configures model-mpc)"),
    (mpc_cli, ["--method", "model-mpc", "--identify-every", "2"],
     "--identify-every has no effect with --method model-mpc"),
    (mpc_cli, ["--method", "ppo-robust"], "--method ppo-robust is run by ftc.controller"),
])
def test_an_option_without_effect_is_refused(tool, argv, message, capsys):
    with pytest.raises(SystemExit) as e:
        tool.parse_args([*argv, *NO_PLANT])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err


def test_an_option_with_effect_is_taken():
    cfg, _ = controller_cli.parse_args(["--method", "ppo-robust", "--teacher-rounds", "1",
                                        *NO_PLANT])
    assert cfg.teacher_rounds == 1
    cfg = mpc_cli.parse_args(["--method", "model-mpc", "--planner", "cem", "--cem-iterations",
                              "2", "--model-episodes", "3", *NO_PLANT])
    assert (cfg.cem_iterations, cfg.model_episodes) == (2, 3)


@pytest.mark.parametrize("tool", [controller_cli, mpc_cli])
def test_an_unknown_method_lists_the_names(tool, capsys):
    with pytest.raises(SystemExit) as e:
        tool.parse_args(["--method", "nope", *NO_PLANT])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "--method nope: unknown" in err and all(n in err for n in registry.METHODS)
    with pytest.raises(ValueError, match="unknown method 'nope'; the methods: closed, open"):
        registry.method("nope")


def test_a_run_of_a_former_name_reads_back(tmp_path):
    (tmp_path / "config.json").write_text(json.dumps({"mpc": {"method": "adaptive"}}))
    assert read_run_configs(str(tmp_path), {"mpc": MPCConfig})["mpc"].method == "identified-mpc"


def test_a_ppo_run_ignores_the_robust_options_its_config_json_held(tmp_path):
    import dataclasses
    doc = {"controller": dataclasses.asdict(RobustConfig(method="ppo")),
           "ppo": dataclasses.asdict(PPOConfig())}
    (tmp_path / "config.json").write_text(json.dumps(doc))
    cfg, _ = controller_cli.resume_config(str(tmp_path))
    assert type(cfg).__name__ == "ControllerConfig" and not hasattr(cfg, "teacher_rounds")
