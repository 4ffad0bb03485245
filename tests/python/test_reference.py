"""The two-stage planner (the best of 4,096 plans and the hold plans, checked
against a brute-force evaluation, never below the H3 hold plan on its own
evaluation), ``--method reference`` on the MPC tool (the episode planner:
tests/python/test_episode_planner.py), and the run
cache the benchmark keeps its runs in (a hit on the same bytes, a miss on a
changed byte, one run for every seed of a scenario)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ftc import _core
from ftc.control import registry
from ftc.tools import mpc as mpc_cli
from ftc.control.planning.physics.evaluators import OracleEvaluator
from ftc.control.planning.planners import (HoldPlanner, TwoStagePlanner, two_stage_candidates,
                                  valve_settings)
from ftc.experiments import run_cache
from ftc.experiments.run_cache import RunCache, RunKey

NO_PLANT = ["--scenario", "", "--link", "core"]


def _weights_evaluator(seed: int):
    """A synthetic evaluator with a known, non-separable total per sequence:
    per-step valve weights and a penalty on switching settings."""
    rng = np.random.default_rng(seed)

    def evaluate(x0, sequences):
        seq = np.asarray(sequences, float)
        w = rng_w[: seq.shape[1]]
        switches = np.abs(np.diff(seq, axis=1)).sum((1, 2))
        return (seq * w).sum((1, 2)) - 0.3 * switches

    rng_w = rng.normal(size=(32, 6))
    return evaluate


def _brute_force(evaluate, x0, plans: np.ndarray) -> float:
    """The best total of ``plans`` (K, L, 6), each evaluated on its own."""
    return max(float(evaluate(x0, plans[k:k + 1])[0]) for k in range(len(plans)))


def test_the_candidates_are_every_first_and_second_setting():
    c = two_stage_candidates(2, 8)
    assert c.shape == (64, 64, 8, 6)
    s = valve_settings()
    assert (c[5, 9, :2] == s[5]).all() and (c[5, 9, 2:] == s[9]).all()
    assert len({c[a, b].tobytes() for a in range(64) for b in range(64)}) == 4096
    short = two_stage_candidates(3, 2)  # no second stage: each setting held throughout
    assert short.shape == (64, 1, 2, 6) and (short[7, 0] == s[7]).all()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_it_finds_the_best_of_the_4096_plans_and_the_hold_plans(seed):
    evaluate = _weights_evaluator(seed)
    x0 = np.zeros(6)
    planner = TwoStagePlanner(first_hold=2, keep=64, hold=3, horizon=8)
    u, seq, total = planner.plan(evaluate, x0)
    every = np.concatenate([planner.hold.candidates(8),
                            two_stage_candidates(2, 8).reshape(-1, 8, 6)])
    assert total == pytest.approx(_brute_force(evaluate, x0, every), abs=1e-12)
    assert float(evaluate(x0, seq[None])[0]) == pytest.approx(total, abs=1e-12)
    assert (u == seq[0]).all()


def test_on_the_true_physics_it_is_the_brute_force_best_and_never_below_the_hold_plan():
    scenario = _core.load_scenario(str(Path(__file__).parents[2] / "scenarios" / "multiple.toml"))
    evaluate = OracleEvaluator(scenario, closed_form=True)
    evaluate.set_age(6.0)
    rng = np.random.default_rng(0)
    hold = HoldPlanner(3, 8)
    full = TwoStagePlanner(2, 64, 3, 8)
    pruned = TwoStagePlanner(2, 8, 3, 8)
    plans = np.concatenate([hold.candidates(8), full.candidates(8).reshape(-1, 8, 6)])
    for i, x0 in enumerate(rng.uniform(0.0, 1.0, (6, 6))):
        _, _, total = full.plan(evaluate, x0)
        if i < 2:  # 4,160 separate rollouts: no prefix shared with another candidate
            assert total == pytest.approx(_brute_force(evaluate, x0, plans), abs=1e-9)
        _, _, h3 = hold.plan(evaluate, x0)
        _, _, kept = pruned.plan(evaluate, x0)
        assert h3 <= kept <= total


def test_pruning_expands_only_the_best_first_settings():
    calls = []
    base = _weights_evaluator(3)

    def evaluate(x0, sequences):
        calls.append(len(sequences))
        return base(x0, sequences)

    TwoStagePlanner(2, 8, 3, 8).plan(evaluate, np.zeros(6))
    assert calls == [64, 8 * 64]


def test_method_reference_is_the_oracle_mpc_with_the_episode_planner(tmp_path):
    ref = mpc_cli.parse_args(["--method", "reference", *NO_PLANT, "--out", str(tmp_path / "r")])
    oracle = mpc_cli.parse_args(["--method", "oracle-mpc", *NO_PLANT, "--out", str(tmp_path / "o")])
    assert (ref.method, ref.planner, ref.rollout_closed_form) == ("reference", "episode", True)
    assert type(ref) is type(oracle)  # the oracle's options, two of them fixed
    assert (oracle.planner, oracle.hold, oracle.horizon) == ("hold", 3, 10)
    # the closed loop it must beat is the oracle's H = 3, L = 10 hold planner
    assert (ref.hold, ref.horizon) == (oracle.hold, oracle.horizon)
    m = registry.METHODS["reference"]
    assert m.cached and m.knows == "the true faults"
    assert m.agent == registry.METHODS["oracle-mpc"].agent
    assert dict(m.options) == {"planner": "episode", "rollout_closed_form": True}
    assert "reference" in registry.tool_methods("ftc.mpc")


def test_a_short_reference_run_finishes(tmp_path, scenarios):
    out = tmp_path / "run"
    proc = subprocess.run([sys.executable, "-m", "ftc.mpc", "--method", "reference",
                           "--scenario", str(scenarios / "multiple.toml"), "--intervals", "1",
                           "--steps-per-interval", "8", "--no-evaluate", "--link", "core",
                           "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert json.loads((out / "config.json").read_text())["mpc"]["planner"] == "episode"


# ---------------------------------------------------------------------------
# The run cache
# ---------------------------------------------------------------------------

def _key(text: str = "name = 'x'\n", code=(("a.py", "0" * 64),), seed=None) -> RunKey:
    return RunKey(text, ("--method", "reference"), 2, 64, "core", seed, code)


def _finished_run(path: Path, value: str) -> Path:
    path.mkdir(parents=True)
    (path / "metrics.csv").write_text(value)
    (path / "result.json").write_text(json.dumps({"status": "ok"}))
    return path


def test_the_cache_hits_on_the_same_bytes_and_misses_on_a_changed_byte(tmp_path):
    cache = RunCache(tmp_path / "cache")
    run = _finished_run(tmp_path / "run", "interval\n0\n")
    assert cache.store(_key(), run) and not cache.store(_key(), run)
    assert cache.restore(_key(), tmp_path / "back")
    assert (tmp_path / "back" / "metrics.csv").read_text() == "interval\n0\n"
    assert not cache.restore(_key("name = 'y'\n"), tmp_path / "miss")  # the scenario's text
    assert not cache.restore(_key(code=(("a.py", "1" + "0" * 63),)), tmp_path / "miss")
    assert not cache.restore(_key(seed=0), tmp_path / "miss")
    assert not (tmp_path / "miss").exists()
    assert not RunCache(None).restore(_key(), tmp_path / "none")
    assert json.loads((cache.entry(_key()) / "key.json").read_text())["args"] == [
        "--method", "reference"]


def test_the_code_digest_changes_with_any_module_of_the_package(tmp_path):
    """The key covers what a cached run imports: a byte changed in the lockstep
    loop (which computes the reward and the episode ends), in the reward itself,
    or in a module added to the package misses; the same bytes elsewhere hit."""
    package = Path(run_cache.__file__).resolve().parents[1]
    copy = tmp_path / "ftc"
    shutil.copytree(package, copy, ignore=shutil.ignore_patterns("__pycache__", "*.so", "bin"))
    digests = run_cache.code_digests(copy)
    assert digests["ftc"] == run_cache.code_digests()["ftc"]  # same bytes, other place
    assert len(digests["_core"]) == 64
    seen = {digests["ftc"]}
    for edit in (next(copy.rglob("lockstep.py")), copy / "plant" / "reward.py",
                 copy / "common" / "new_module.py"):
        with open(edit, "a") as f:
            f.write("# changed\n")
        seen.add(run_cache.code_digests(copy)["ftc"])
    assert len(seen) == 4


def _benchmark(out: Path, scenario: Path, cache: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "ftc.experiments", "benchmark", "--scenarios", str(scenario),
         "--methods", "closed", "--seeds", "0", "1", "--intervals", "1",
         "--steps-per-interval", "16", "--jobs", "1", "--run-cache", str(cache),
         "--out", str(out)], capture_output=True, text=True, timeout=600)


def _reference_rows(out: Path) -> list[tuple[str, str]]:
    import csv

    with open(out / "results.csv", newline="") as f:
        return [(r["seed"], r["reward_per_step"]) for r in csv.DictReader(f)
                if r["method"] == "reference"]


@pytest.mark.slow  # 10-30 s: the fresh-clone CI stays under its 10 minutes
def test_the_benchmark_runs_the_reference_once_per_scenario_and_then_from_the_cache(
        tmp_path, scenarios):
    scenario = tmp_path / "single.toml"
    scenario.write_text((scenarios / "single.toml").read_text())
    cache = tmp_path / "cache"
    first = tmp_path / "first"
    assert _benchmark(first, scenario, cache).returncode == 0
    meta = json.loads((first / "benchmark.json").read_text())
    assert meta["config"]["reference"] == "reference"
    sources = meta["run_cache"]["sources"]
    assert sources["single/t00/reference/s0"]["from"] == "ran"
    assert sources["single/t00/reference/s1"]["from"] == "single/t00/reference/s0"
    assert set(meta["run_cache"]["code"]) == {"ftc", "_core", "plant"}
    rows = _reference_rows(first)
    assert [s for s, _ in rows] == ["0", "1"] and rows[0][1] == rows[1][1]
    # the same bytes: nothing of the reference runs
    second = tmp_path / "second"
    assert _benchmark(second, scenario, cache).returncode == 0
    meta = json.loads((second / "benchmark.json").read_text())
    assert meta["run_cache"]["sources"]["single/t00/reference/s0"]["from"] == "cache"
    started = [json.loads((d / "runs" / "single" / "t00" / "reference" / "s0" / "result.json"
                           ).read_text())["started"] for d in (first, second)]
    assert started[0] == started[1] and _reference_rows(second) == rows
    # one byte more (a comment): a miss, run again
    scenario.write_text(scenario.read_text() + "#\n")
    third = tmp_path / "third"
    assert _benchmark(third, scenario, cache).returncode == 0
    meta = json.loads((third / "benchmark.json").read_text())
    assert meta["run_cache"]["sources"]["single/t00/reference/s0"]["from"] == "ran"
    assert len(list(cache.iterdir())) == 2
