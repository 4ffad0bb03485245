"""ppo-robust (control/agents/physics/ppo_robust.py): the planner-guided offline phase
makes a policy that starts from scratch act as the planner on the identified
physics, plans each distinct level once, and stops its fits early when told."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ftc import _core
from ftc.control.planning.physics.evaluators import ParamsEvaluator
from ftc.control.agents.learned.guided_ppo import PlanCache
from ftc.control.agents.physics.ppo_robust import _same_plan

REPO = Path(__file__).resolve().parents[2]


def _run(tmp_path: Path, name: str, *extra: str) -> list[dict]:
    out = tmp_path / name
    cmd = [sys.executable, "-m", "ftc.controller", "--method", "ppo-robust", "--link", "core",
           "--scenario", str(REPO / "scenarios" / "single.toml"), "--seed", "0",
           "--intervals", "2", "--steps-per-interval", "128", "--update-every", "64",
           "--offline-steps", "0", "--ppo-engine", "native", "--teacher-states", "256",
           "--teacher-refits", "0", "--out", str(out), "--quiet", *extra]
    subprocess.run(cmd, check=True, cwd=REPO, timeout=600)
    return list(csv.DictReader(open(out / "metrics.csv")))


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("robust")
    # "full" and "early": one fit's DAgger (deterministic rollouts, no memory of
    # earlier fits); "memory": the defaults (sampled rollouts, memory of earlier fits)
    single_fit = ("--no-teacher-sample", "--teacher-memory", "0")
    return {"full": _run(tmp, "full", "--teacher-epochs", "60", "--teacher-stop-loss", "0",
                         *single_fit),
            "early": _run(tmp, "early", "--teacher-epochs", "60", "--teacher-stop-loss", "0.5",
                          *single_fit),
            "memory": _run(tmp, "memory", "--teacher-epochs", "20", "--teacher-memory", "100")}


def test_the_guided_fit_makes_a_fresh_policy_act_as_the_planner(runs):
    rows = runs["full"]
    # interval 0: a fresh policy opens each valve with p ~ 0.5 (random valves earn
    # ~1.87 per step on this plant, all closed 2.68); after interval 0's guided fit
    # the policy agrees with the planner on nearly every valve of the labelled
    # levels and earns far more in interval 1 (planner ~2.6 at age 1)
    assert float(rows[0]["reward_per_step"]) < 2.1
    assert float(rows[0]["distill_agreement"]) > 0.95
    assert float(rows[1]["reward_per_step"]) > float(rows[0]["reward_per_step"]) + 0.3
    assert int(rows[0]["distill_epochs"]) == 60  # stop loss 0: every epoch


def test_each_distinct_level_is_planned_once(runs):
    for row in runs["full"]:
        labels, plans = int(row["teacher_labels"]), int(row["teacher_plans"])
        # episodes repeat from full tanks: far fewer distinct levels than labels
        assert 0 < plans < labels


def test_a_stop_loss_ends_the_fits_early(runs):
    # 0.5 nats per valve is crossed within a few epochs (a fresh policy: log 2 = 0.69)
    assert all(int(r["distill_epochs"]) < 60 for r in runs["early"])
    # (its speed is a benchmark's: scripts/bench.py --only robust)


def test_each_fit_keeps_a_bounded_memory_of_the_levels_earlier_fits_labelled(runs):
    memory = [int(r["teacher_memory"]) for r in runs["memory"]]
    assert memory[0] == 0          # the first fit has no earlier one
    assert memory[1] == 100        # then the 100 most recent distinct levels (the limit)
    assert all(int(r["teacher_memory"]) == 0 for r in runs["full"])  # --teacher-memory 0


def test_recent_distinct_keeps_the_last_occurrences_most_recent_last():
    import numpy as np

    from ftc.control.agents.learned.guided_ppo import _recent_distinct

    a, b, c, d = (np.full(6, v) for v in (0.1, 0.2, 0.3, 0.4))
    rows = np.array([a, b, a, c, d, c])
    np.testing.assert_array_equal(_recent_distinct(rows, 10), [b, a, d, c])
    np.testing.assert_array_equal(_recent_distinct(rows, 2), [d, c])
    assert _recent_distinct(rows, 0).shape == (0, 6)


def test_the_memory_survives_a_checkpoint():
    import numpy as np

    from ftc.tools.controller import make_agent, parse_args

    cfg, ppo = parse_args(["--method", "ppo-robust", "--link", "core", "--out", "unused"])
    agent = make_agent(cfg, ppo)
    agent.memory = np.random.default_rng(0).random((7, 6))
    again = make_agent(cfg, ppo)
    again.load_state_dict(agent.state_dict())
    np.testing.assert_array_equal(again.memory, agent.memory)


def test_the_check_prices_a_policy_that_strands_fuel_behind_a_dead_pump():
    # tank 5's pump dead, the others empty: with every valve closed the fuel never
    # reaches an engine and the reward is 0 per step for good; the planner opens
    # valves to move it (measured: 19 of reward over its 10 steps). At full tanks
    # closing everything is the planner's own choice: no regret.
    import numpy as np
    import torch

    from ftc.tools.controller import make_agent, parse_args

    cfg, ppo = parse_args(["--method", "ppo-robust", "--link", "core", "--out", "unused"])
    agent = make_agent(cfg, ppo)
    agent.teacher_eval.params = {"pump": np.array([0.1, 0.1, 0.1, 0.1, 0.0, 0.1]),
                                 "resistance": np.full(6, 100.0),
                                 "demand": np.array([0.07, 0.07])}
    with torch.no_grad():  # a policy that closes every valve everywhere
        last = [m for m in agent.ppo.policy.modules() if isinstance(m, torch.nn.Linear)]
        head = [m for m in last if m.out_features == 6][-1]
        head.weight.zero_()
        head.bias.fill_(-10.0)
    from ftc.control.agents.learned.guided_ppo import regret

    def price(level):
        return regret(agent.ppo, agent.teacher, agent.teacher_eval, level)

    stranded = price(np.array([0.0, 0.0, 0.0, 0.0, 0.163, 0.0]))
    assert stranded > cfg.teacher_check_regret
    assert stranded == pytest.approx(18.96, abs=0.05)
    assert price(np.full(6, 1.0)) == 0.0


def test_labels_are_kept_only_for_the_parameters_they_were_planned_with():
    # a refit after a check plans on the parameters of the fit before it: its
    # labels are reused; other parameters, or a valve seen stuck, drop them
    evaluate = ParamsEvaluator(_core.BatchRollout())
    evaluate.params = _core.degraded_params(_core.load_scenario(str(REPO / "scenarios" /
                                                                    "single.toml")), 2.0)
    cache = PlanCache()
    cache.begin((evaluate.params, dict(evaluate.stuck)), _same_plan)
    cache.labels[b"level"] = np.ones(6)
    evaluate.params = {k: np.array(v, copy=True) for k, v in evaluate.params.items()}
    cache.begin((evaluate.params, dict(evaluate.stuck)), _same_plan)  # equal values in a new dict: kept
    assert b"level" in cache.labels
    evaluate.stuck[2] = 1
    cache.begin((evaluate.params, dict(evaluate.stuck)), _same_plan)  # a stuck valve changes every plan: dropped
    assert not cache.labels
    cache.labels[b"level"] = np.ones(6)
    evaluate.params = {**evaluate.params, "pump": np.asarray(evaluate.params["pump"]) * 0.5}
    cache.begin((evaluate.params, dict(evaluate.stuck)), _same_plan)  # other parameters: dropped
    assert not cache.labels
