"""The one registry of methods (ftc.control.registry), methods as data: every
method builds its config and agent; a method's command line offers exactly its
own options, so every option given acts on the run and any other is refused
(walked: every method against every option of its tool); a variant is its
entry's option values, not rewritten argv; former names warn and map; an
unknown method is named with the list of known ones; figures' colours come
from the registry."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import pytest

from ftc.common.cli import NONZERO, needs, unmet
from ftc.control import registry
from ftc.control.agents.mpc_config import MPCConfig
from ftc.control.agents.physics.mpc import ModelMPCConfig
from ftc.control.agents.ppo import ControllerConfig
from ftc.control.agents.learned.guided_ppo import GuidedConfig
from ftc.control.run.agent import Agent
from ftc.control.run.config import RunConfig
from ftc.control.run.metrics import metric_columns
from ftc.experiments import figures
from ftc.experiments.methods import METHODS as EXPERIMENT_METHODS
from ftc.learning.ppo import PPOConfig
from ftc.tools import controller as controller_cli
from ftc.tools import mpc as mpc_cli
from ftc.tools.run_cli import read_run_configs

NO_PLANT = ["--scenario", "", "--link", "core"]
TOOLS = {"ftc.controller": controller_cli, "ftc.mpc": mpc_cli}


def _parse(tool: str, argv: list[str]) -> dict:
    if tool == "ftc.controller":
        cfg, ppo = controller_cli.parse_args(argv)
        return {"controller": cfg, "ppo": ppo}
    return {"mpc": mpc_cli.parse_args(argv)}


@pytest.mark.parametrize("name", list(registry.METHODS))
def test_every_method_builds_its_config_and_agent(name, tmp_path):
    m = registry.METHODS[name]
    configs = _parse(m.tool, [*m.args, *NO_PLANT, "--out", str(tmp_path / m.name)])
    cfg = configs[m.part]
    assert type(cfg) is m.config_class() and cfg.method == name
    assert all(getattr(cfg, k) == v for k, v in m.options.items())  # the variant's values
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


def _options(tool: str) -> dict[str, tuple[str, object, str]]:
    """Every option of ``tool``'s methods (run options aside): flag -> (field,
    default, part prefix)."""
    run = {f.name for f in dataclasses.fields(RunConfig)}
    out = {}
    for name in registry.tool_methods(tool):
        m = registry.method(name)
        for cls, prefix in [(m.config_class(), ""), *m.agent_class().parts.values()]:
            for f in dataclasses.fields(cls):
                if f.name not in run and f.name != "method":
                    out.setdefault(f"--{prefix}{f.name.replace('_', '-')}", (f.name, f, prefix))
    return out


SAMPLES = {"pretrain_lr": "0.001", "push_policy": "RT_", "target_kl": "0.02"}
# what an option of a part needs beside it (PPOConfig.validate: value clipping is the torch
# engine's)
WITH = {"--ppo-clip-vloss": ["--ppo-engine", "torch"]}


def _given(flag: str, f: dataclasses.Field) -> list[str]:
    """``flag`` with a valid value other than its default where one is at hand."""
    if f.type in (bool, "bool"):
        return [flag.replace("--", "--no-", 1) if f.default else flag]
    if f.name in SAMPLES:
        return [flag, SAMPLES[f.name]]
    if isinstance(f.default, tuple):
        return [flag, *map(str, f.default)]
    choices = f.metadata.get("choices")
    if choices:
        return [flag, next((c for c in choices if c != f.default), f.default)]
    return [flag, str(f.default)]


@pytest.mark.parametrize("tool", list(TOOLS))
def test_every_method_against_every_option(tool, tmp_path, capsys, monkeypatch):
    """No option is accepted without effect: each method's command line takes
    an option of its tool exactly when its run config (or a part of it) has the
    field, its method does not fix it, and what it acts with is given (an option
    that acts only with another's value is refused without it, and taken with it);
    every other is refused, exit 2, one line naming the option and the method."""
    key = tmp_path / "bus.key"  # --push-key-file's value: a key file, mode 600
    key.write_text("ab" * 32)
    key.chmod(0o600)
    monkeypatch.setitem(SAMPLES, "push_key_file", str(key))
    walked = 0
    for name in registry.tool_methods(tool):
        m = registry.method(name)
        own = {f"--{prefix}{n.replace('_', '-')}" for cls, prefix in
               [(m.config_class(), ""), *m.agent_class().parts.values()]
               for n in [f.name for f in dataclasses.fields(cls)]
               if prefix or (n in m.offered())}
        wants = needs(m.config_class())
        for flag, (field, f, prefix) in _options(tool).items():
            walked += 1
            argv = ["--method", name, *NO_PLANT, "--out", str(tmp_path / "x"), *_given(flag, f),
                    *WITH.get(flag, [])]
            need = None if prefix else wants.get(field)
            if flag not in own:
                with pytest.raises(SystemExit) as e:
                    _parse(tool, argv)
                err = capsys.readouterr().err.strip().splitlines()
                assert e.value.code == 2 and len(err) == 1, (name, flag, err)
                assert f"{_given(flag, f)[0]} is not an option of --method {name}" in err[0], err
                continue
            if need is not None:
                if field in unmet(m.config({})):  # not met by the defaults: give what it needs
                    dep, value = next((d, v) for d, v in (
                        need if isinstance(need, list) else [need]) if d not in m.options)
                    with pytest.raises(SystemExit) as e:
                        _parse(tool, argv)
                    err = capsys.readouterr().err.strip().splitlines()
                    assert e.value.code == 2 and f"{flag} has no effect" in err[-1], (name, err)
                    if value is NONZERO:  # any value of the option it needs
                        value = SAMPLES[dep]
                    argv += [f"--{dep.replace('_', '-')}"] + ([] if value is True else [value])
            configs = _parse(tool, argv)
            part = configs["ppo"] if prefix else configs[m.part]
            assert getattr(part, field) == _parsed_value(f, _given(flag, f)), (name, flag)
            assert field not in unmet(configs[m.part]), (name, flag)
    assert walked >= (150 if tool == "ftc.controller" else 100)


def _parsed_value(f: dataclasses.Field, given: list[str]):
    if f.type in (bool, "bool"):
        return not f.default
    words = given[1:]
    kind = str(f.type)
    if kind.startswith("tuple[int"):
        return tuple(int(w) for w in words)
    convert = int if kind == "int" else float if "float" in kind else str
    return convert(words[0])


def test_a_variant_is_its_entrys_option_values_not_argv():
    """ppo-online is ppo with the offline phase fixed off: its command line
    offers neither --offline nor the options of the offline phase."""
    online, ppo = registry.method("ppo-online"), registry.method("ppo")
    assert online.agent == ppo.agent and dict(online.options) == {"offline": False}
    assert "offline" not in online.offered() and "model_window" not in online.offered()
    assert {"offline", "model_window", "model_engine", "model_episodes",
            "offline_mode"} <= set(ppo.offered())
    guided = set(registry.method("ppo-robust").offered())
    assert not guided & {"offline", "offline_mode", "model_window", "model_engine",
                         "model_episodes"}  # Algorithm 1's offline phase, not theirs
    assert set(registry.method("closed").offered()) == \
        {f.name for f in dataclasses.fields(RunConfig)}
    assert "band" in registry.method("balance").offered()


def test_no_agent_imports_the_registry():
    """The agents name no methods: the registry names them (no import circle)."""
    import ast
    from pathlib import Path

    import ftc.control
    root = Path(ftc.control.__file__).parent

    def imports_registry(path: Path) -> bool:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (
                    node.module == "ftc.control.registry" or (node.module == "ftc.control" and any(
                        a.name == "registry" for a in node.names))):
                return True
            if isinstance(node, ast.Import) and any(a.name == "ftc.control.registry"
                                                    for a in node.names):
                return True
        return False

    assert imports_registry(Path(controller_cli.__file__))  # the check sees such an import
    assert [p.relative_to(root) for p in root.rglob("*.py") if imports_registry(p)] == []


def test_figures_take_the_registrys_colours():
    assert figures.METHOD_COLORS == registry.colors()
    assert figures.METHOD_COLORS["oracle-mpc"] == registry.method("oracle-mpc").color


@pytest.mark.parametrize("name", [n for n, m in registry.METHODS.items() if m.compared])
def test_the_experiments_start_each_method_as_the_registry_says(name):
    spec, m = EXPERIMENT_METHODS[name], registry.METHODS[name]
    assert (spec.module, spec.args, spec.label, spec.cost) == (m.tool, m.args, m.label, m.cost)


@pytest.mark.parametrize("alias,name", sorted(registry.ALIASES.items()))
def test_a_former_name_warns_and_maps(alias, name, capsys, tmp_path):
    cfg = mpc_cli.parse_args(["--method", alias, *NO_PLANT, "--out", str(tmp_path / "x")])
    assert cfg.method == name
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"ftc.mpc: warning: --method {alias} is deprecated; use --method {name}"]
    assert registry.method(alias) is registry.METHODS[name]


@pytest.mark.parametrize("tool,argv,message", [
    (controller_cli, ["--method", "ppo", "--teacher-rounds", "1"],
     "--teacher-rounds is not an option of --method ppo"),
    (controller_cli, ["--method", "closed", "--offline-steps", "8"],
     "--offline-steps is not an option of --method closed"),
    (controller_cli, ["--method", "ppo-robust", "--model-window", "2"],
     "--model-window is not an option of --method ppo-robust"),
    (controller_cli, ["--method", "ppo-offline", "--pretrain-lr", "0.1"],
     "--pretrain-lr has no effect without --pretrain"),
    (controller_cli, ["--method", "ppo", "--no-offline", "--model-window", "2"],
     "--model-window has no effect without --offline"),
    (controller_cli, ["--method", "ppo-online", "--offline"],
     "--offline is not an option of --method ppo-online"),
    (controller_cli, ["--method", "oracle-mpc"], "--method oracle-mpc is run by ftc.mpc"),
    (mpc_cli, ["--method", "oracle-mpc", "--cem-iterations", "2"],
     "--cem-iterations has no effect with --planner hold"),
    (mpc_cli, ["--method", "oracle-mpc", "--model-episodes", "2"],
     "--model-episodes is not an option of --method oracle-mpc"),
    (mpc_cli, ["--method", "model-mpc", "--planner", "episode"], "invalid choice: 'episode'"),
    (mpc_cli, ["--method", "reference", "--planner", "hold"],
     "--planner is not an option of --method reference"),
    (mpc_cli, ["--method", "ppo-robust"], "--method ppo-robust is run by ftc.controller"),
])
def test_an_option_of_another_method_is_refused(tool, argv, message, capsys):
    with pytest.raises(SystemExit) as e:
        tool.parse_args([*argv, *NO_PLANT])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err


def test_help_with_a_method_lists_its_options(capsys):
    for tool, name, has, lacks in [(controller_cli, "ppo-robust", "--teacher-rounds",
                                    "--model-window"),
                                   (controller_cli, "balance", "--band", "--ppo-gamma"),
                                   (mpc_cli, "learned-mpc", "--learn-forget", "--identify-every")]:
        with pytest.raises(SystemExit):
            tool.parse_args(["--method", name, "--help"])
        text = capsys.readouterr().out
        assert has in text and lacks not in text and f"Options of --method {name}" in text


def test_an_option_with_effect_is_taken():
    cfg, _ = controller_cli.parse_args(["--method", "ppo-robust", "--teacher-rounds", "1",
                                        *NO_PLANT])
    assert cfg.teacher_rounds == 1
    cfg, _ = controller_cli.parse_args(["--method", "balance", "--band", "0.25", *NO_PLANT])
    assert cfg.band == 0.25
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


def test_a_stored_run_drops_the_options_its_method_never_read(tmp_path):
    """Runs written when every method's config held every option read back as
    their method's config: the others' fields dropped, an unknown one refused."""
    doc = {"controller": {**dataclasses.asdict(GuidedConfig(method="ppo")),
                          **dataclasses.asdict(ControllerConfig(method="ppo"))},
           "ppo": dataclasses.asdict(PPOConfig())}
    (tmp_path / "config.json").write_text(json.dumps(doc))
    cfg, _ = controller_cli.resume_config(str(tmp_path))
    assert type(cfg) is ControllerConfig and not hasattr(cfg, "teacher_rounds")
    doc["controller"]["method"] = "closed"
    (tmp_path / "config.json").write_text(json.dumps(doc))
    cfg, _ = controller_cli.resume_config(str(tmp_path))
    assert not hasattr(cfg, "update_every") and cfg.method == "closed"
    doc["controller"]["no_such_option"] = 1
    (tmp_path / "config.json").write_text(json.dumps(doc))
    from ftc.common.errors import CheckpointError
    with pytest.raises(CheckpointError, match="unknown options no_such_option"):
        controller_cli.resume_config(str(tmp_path))
    assert ModelMPCConfig().method == "model-mpc"


def test_a_checkpoint_written_before_an_option_existed_resumes_at_its_default(tmp_path):
    """balance's --band is new: a run checkpointed without it had the rule's 0.1,
    so it resumes under the default and is refused under another band."""
    import torch

    out = tmp_path / "run"
    common = ["--link", "core", "--quiet", "--scenario", ""]
    assert controller_cli.main(["--method", "balance", "--intervals", "1",
                                "--steps-per-interval", "16", *common, "--out", str(out)]) == 0
    state = torch.load(out / "checkpoint.pt", weights_only=True)
    del state["config"]["controller"]["band"]  # as a checkpoint of the code before
    torch.save(state, out / "checkpoint.pt")
    config = json.loads((out / "config.json").read_text())
    del config["controller"]["band"]
    (out / "config.json").write_text(json.dumps(config))
    assert controller_cli.main(["--resume", str(out), "--intervals", "2", "--quiet"]) == 0
    state = torch.load(out / "checkpoint.pt", weights_only=True)
    del state["config"]["controller"]["band"]
    torch.save(state, out / "checkpoint.pt")
    (out / "done.json").unlink()
    config["controller"]["band"] = 0.2  # a run that claims another band: not this checkpoint's
    (out / "config.json").write_text(json.dumps(config))
    assert controller_cli.main(["--resume", str(out), "--intervals", "3", "--quiet"]) == 2
