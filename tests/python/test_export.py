"""python -m ftc.export: the PPO policy of a real controller checkpoint (a short
run over LCM against the plant process) exported to ONNX, run in onnxruntime
and compared with the agent's own deterministic actions on thousands of
states; bad input (missing, truncated, a run without a policy, a bad --out)
is one line, exit 2, and no file."""

from __future__ import annotations

import io
import json
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import numpy as np
import onnx
import onnxruntime
import pytest
import torch

from ftc.tools import controller as controller_cli

from ftc.tools import mpc as mpc_cli
from ftc.control.run.agent import StepContext
from ftc.control.agents.ppo import ControllerConfig, PPOAgent
from ftc.learning.ppo import PPOConfig
from ftc.plant.link import PlantObservation
from ftc.tools import export

# onnxruntime vs torch on the logits, both float32 (measured: at most 2.4e-7; the smallest
# |logit| in the test's sample is 1.2e-5, so no decision is a near tie)
LOGIT_ATOL = 1e-5
SHORT = ["--intervals", "2", "--steps-per-interval", "128", "--update-every", "64",
         "--offline-steps", "512", "--offline-envs", "8", "--offline-rollout", "32",
         "--model-episodes", "6", "--seed", "3", "--quiet"]


def _quiet(main, argv: list[str]) -> tuple[int, str]:
    err = io.StringIO()
    with redirect_stderr(err), redirect_stdout(io.StringIO()):
        try:
            code = main(argv)
        except SystemExit as e:
            code = e.code
    return code, err.getvalue()


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> tuple[Path, Path]:
    """(run directory, policy.onnx) of a short PPO run over LCM."""
    root = tmp_path_factory.mktemp("export")
    run = root / "run"
    scenario = Path(__file__).resolve().parents[2] / "scenarios" / "single.toml"
    assert controller_cli.main(["--scenario", str(scenario), "--out", str(run), *SHORT]) == 0
    onnx_path = root / "policy.onnx"
    assert export.main([str(run / "checkpoint.pt"), "--out", str(onnx_path)]) == 0
    return run, onnx_path


def _agent(run: Path) -> PPOAgent:
    """The run's PPO agent, restored the way --resume restores it."""
    doc = json.loads((run / "config.json").read_text())
    cfg = ControllerConfig(**{k: tuple(v) if isinstance(v, list) else v
                              for k, v in doc["controller"].items()})
    ppo = PPOConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in doc["ppo"].items()})
    agent = PPOAgent(cfg, ppo)
    agent.load_state_dict(torch.load(run / "checkpoint.pt", weights_only=True)["agent"])
    return agent


def _states(n: int) -> np.ndarray:
    """Levels over the observation space and a little beyond it (sensor noise
    around empty and full tanks), float32 (n, 6)."""
    rng = np.random.default_rng(1234)
    inside = rng.uniform(0.0, 1.0, (n // 2, 6))
    edges = rng.uniform(-0.05, 1.05, (n - n // 2, 6))
    return np.concatenate([inside, edges]).astype(np.float32)


def test_onnxruntime_takes_the_agents_deterministic_actions(exported):
    run, path = exported
    model = onnx.load(str(path))
    onnx.checker.check_model(model, full_check=True)
    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    (inp,), outs = session.get_inputs(), session.get_outputs()
    assert (inp.name, inp.type, inp.shape[1]) == ("levels", "tensor(float)", 6)
    assert [(o.name, o.type, o.shape[1]) for o in outs] == [
        ("valves", "tensor(int8)", 6), ("logits", "tensor(float)", 6)]
    assert isinstance(inp.shape[0], str)  # a dynamic batch dimension

    agent = _agent(run)
    x = _states(5000)
    valves, logits = session.run(None, {"levels": x})
    with torch.no_grad():
        want_valves, _, _ = agent.ppo.act(torch.from_numpy(x), deterministic=True)
        want_logits, _ = agent.ppo.policy(torch.from_numpy(x))
    assert valves.dtype == np.int8 and valves.shape == (5000, 6)
    np.testing.assert_array_equal(valves, want_valves.numpy().astype(np.int8))
    np.testing.assert_allclose(logits, want_logits.numpy(), rtol=0, atol=LOGIT_ATOL)
    # the sample has decisions both ways, on every valve (not a constant policy)
    assert (valves.min(axis=0) == 0).all() and (valves.max(axis=0) == 1).all()
    assert set(np.unique(valves)) == {0, 1}

    # one state at a time, as a C++ controller runs it, through the agent's act()
    for level in x[:200]:
        obs = PlantObservation(level=level.astype(np.float64), true_level=level,
                               valves=np.zeros(6, np.int8), deficit=np.zeros(2), age=0.0,
                               step=0, episode=0, operating_steps=0, terminal=False,
                               truncated=False, evaluation=True)
        u = agent.act(obs, StepContext(0, 0, None, evaluation=True))
        (one,), _ = session.run(None, {"levels": level[None]})
        np.testing.assert_array_equal(one, u)


def test_model_records_where_it_came_from(exported):
    run, path = exported
    props = {p.key: p.value for p in onnx.load(str(path)).metadata_props}
    assert props["ftc.method"] == "ppo" and props["ftc.seed"] == "3"
    assert props["ftc.interval"] == "2"  # intervals finished when the checkpoint was written
    assert props["ftc.checkpoint"] == str((run / "checkpoint.pt").resolve())
    assert "ftc.git_revision" in props


def test_a_run_directory_names_its_checkpoint(exported, tmp_path):
    run, path = exported
    out = tmp_path / "again.onnx"
    code, err = _quiet(export.main, [str(run), "--out", str(out), "--verify-states", "0"])
    assert code == 0, err
    assert out.read_bytes() == path.read_bytes()


@pytest.fixture(scope="module")
def policyless(tmp_path_factory) -> dict[str, Path]:
    """Checkpoints of runs without a policy network: a baseline and an MPC."""
    root = tmp_path_factory.mktemp("policyless")
    common = ["--scenario", "", "--intervals", "1", "--steps-per-interval", "32", "--quiet",
              "--link", "core"]
    assert controller_cli.main(["--method", "closed", "--out", str(root / "closed"),
                                *common]) == 0
    assert mpc_cli.main(["--method", "oracle-mpc", "--out", str(root / "oracle"), *common]) == 0
    return {"closed": root / "closed" / "checkpoint.pt",
            "oracle": root / "oracle" / "checkpoint.pt"}


@pytest.mark.parametrize("case", ["missing", "truncated", "not-a-checkpoint", "closed",
                                  "oracle"])
def test_bad_checkpoint_is_one_line_exit_2_and_no_file(exported, policyless, tmp_path, case):
    run, _ = exported
    source = tmp_path / "in.pt"
    if case == "missing":
        source = tmp_path / "nothing-here.pt"
    elif case == "truncated":
        data = (run / "checkpoint.pt").read_bytes()
        source.write_bytes(data[:len(data) // 2])
    elif case == "not-a-checkpoint":
        torch.save({"policy": {}}, source)
    else:
        source = policyless[case]
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    code, err = _quiet(export.main, [str(source), "--out", str(out_dir / "policy.onnx")])
    lines = err.strip().splitlines()
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith("ftc.export: error: "), err
    assert str(source) in lines[0]
    assert {"missing": "no such checkpoint", "truncated": "corrupt or truncated",
            "not-a-checkpoint": "no format record", "closed": "--method closed run",
            "oracle": "mpc --method oracle-mpc"}[case] in lines[0], lines[0]
    assert list(out_dir.iterdir()) == []  # no file, no temporary file


@pytest.mark.parametrize("case", ["a-directory", "under-a-file", "empty"])
def test_bad_out_is_refused_before_the_checkpoint_is_read(exported, tmp_path, case):
    run, _ = exported
    blocker = tmp_path / "blocker"
    blocker.write_text("x\n")
    out = {"a-directory": str(tmp_path), "under-a-file": str(blocker / "p.onnx"),
           "empty": ""}[case]
    code, err = _quiet(export.main, [str(run), "--out", out])
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "--out" in lines[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["blocker"]


def test_the_weights_file_takes_the_agents_deterministic_actions(exported, tmp_path):
    """ftc.export --weights: the file build/policy_node reads, whose arithmetic
    (ftc.tools.policy_weights.actions, the node's) is the trained policy's."""
    from ftc.tools import policy_weights

    run, _ = exported
    out = tmp_path / "policy.txt"
    code, err = _quiet(export.main, [str(run), "--weights", str(out)])
    assert code == 0, err
    widths, params, version = policy_weights.read_weights(out)
    assert widths == [6, 64, 64, 16, 16, 6] and version >= 1
    states = _states(2000)
    agent = _agent(run)
    with torch.no_grad():
        logits, _ = agent.ppo.policy(torch.as_tensor(states))
    clear = (logits.abs() > 1e-4).all(axis=1).numpy()  # rows not within rounding of a tie
    expected = (logits > 0).numpy().astype(np.int8)
    assert np.array_equal(policy_weights.actions(widths, params, states)[clear], expected[clear])
    code, err = _quiet(export.main, [str(run), "--weights", str(out)])
    assert code == 2 and "exists" in err  # an existing file is refused without --overwrite


def test_the_check_allows_float32_rounding_of_large_logits_and_no_more():
    """A distilled policy's logits reach the hundreds: onnxruntime and torch then
    differ by float32's relative rounding (2.1e-5 measured on ppo-robust), which
    the check allows; a model whose weights differ is still refused."""
    from ftc.learning.ppo import ActorCritic
    from ftc.common.errors import RunError

    torch.manual_seed(0)
    policy = ActorCritic()
    with torch.no_grad():
        head = [m for m in policy.policy_head.modules() if isinstance(m, torch.nn.Linear)][-1]
        head.weight.mul_(3e4)  # logits in the hundreds
        head.bias.fill_(0.0)
        logits, _ = policy(torch.from_numpy(export.sample_levels(512)))
    assert float(logits.abs().max()) > 100
    model = export.export_model(policy, {"source": "test"})
    gap = export.verify(model, policy, 512)
    assert 1e-5 < gap < export.LOGIT_ATOL + export.LOGIT_RTOL * float(logits.abs().max())
    other = ActorCritic()
    other.load_state_dict(policy.state_dict())
    with torch.no_grad():
        [m for m in other.policy_head.modules() if isinstance(m, torch.nn.Linear)][-1] \
            .bias.add_(1.0)  # beyond 1e-5 + 1e-5 x the largest logit on every state
    with pytest.raises(RunError, match="logits beyond"):
        export.verify(model, other, 512)
