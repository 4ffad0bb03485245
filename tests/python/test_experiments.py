"""The experiments pipeline end to end on the real plant and the real controller:
a shortened `all` run produces every file and figure; replay of each run's
LCM log reproduces the rewards the controller reported; parallel runs never
hear each other; --resume after a kill keeps finished runs byte for byte; the
figure and report functions work on committed fixture results; a corrupt log
is a clear error.

Shortened protocol: 2 intervals of 64 steps (PPO updates every 32),
2 aggregate trials, 2 jobs, and a small world-model data set for the offline
method, so the module runs in about a minute and a half on two cores.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from ftc import experiments as ex
from ftc.experiments import figures, report
from ftc.plant.log import LogError, read_log

FIXTURE = Path(__file__).resolve().parents[1] / "data" / "experiment_results"
SHORT = ["--intervals", "2", "--steps-per-interval", "64", "--jobs", "2",
         "--controller-args", "--update-every 32 --model-episodes 4 --offline-steps 128"]


def _run_cli(args: list[str], timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ftc.experiments", *args], capture_output=True,
                          text=True, timeout=timeout)


@pytest.fixture(scope="module")
def all_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("exp") / "all"
    proc = _run_cli(["all", "--out", str(out), "--trials", "2", *SHORT])
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out


def test_shortened_all_run_writes_every_file_and_figure(all_run):
    meta = json.loads((all_run / "experiment.json").read_text())
    assert meta["git_revision"] and meta["config"]["trials"] == 2
    assert meta["seeds"] == {"controller": [0], "scenario": ex.ExperimentConfig.scenario_seed}
    assert len(meta["scenarios"]["aggregate"]) == 2
    for name in ("single", "multiple", "aggregate-00", "aggregate-01"):
        assert (all_run / "scenarios" / f"{name}.toml").is_file()
    runs = ex.plan_runs(ex.ExperimentConfig.from_json(meta["config"]))
    n_methods = len(ex.DEFAULT_METHODS)  # the paper's four and the two MPC references
    assert n_methods == 6 and len(runs) == 4 * n_methods  # single, multiple, 2 aggregate
    for spec in runs:
        d = spec.directory(all_run)
        for f in ("result.json", "metrics.csv", "metrics.json", "plant.lcmlog", "controller.log",
                  "controller/config.json", "controller/metrics.csv"):
            assert (d / f).is_file(), f"{spec.key}: missing {f}"
        assert json.loads((d / "result.json").read_text())["status"] == "ok"
        assert len(json.loads((d / "metrics.json").read_text())) == 2
    for stem in ("a_reward_episode", "b_reward_per_interval", "c_tank_control", "d_aggregate"):
        for fmt in ("png", "svg"):
            assert (all_run / "figures" / f"{stem}.{fmt}").stat().st_size > 1000, stem
    md = (all_run / "report.md").read_text()
    for heading in ("Single fault", "Multiple faults", "Aggregate", "Scenarios", "Wall times"):
        assert heading in md
    assert "PPO online + offline" in md and "aggregate-01" in md
    assert "fraction of the oracle" in md
    page = (all_run / "report.html").read_text()
    assert page.count("data:image/png;base64,") == 4
    with open(all_run / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 4 * n_methods * 2  # two intervals per run
    assert {r["method"] for r in rows} == set(ex.DEFAULT_METHODS)


def test_replay_of_each_log_reproduces_the_reported_rewards(all_run):
    for spec in ex.plan_runs(ex.ExperimentConfig.from_json(
            json.loads((all_run / "experiment.json").read_text())["config"])):
        d = spec.directory(all_run)
        traj = read_log(d / "plant.lcmlog")
        assert traj.missing == 0, f"{spec.key}: the log lost messages"
        replayed = traj.reward_per_interval()
        replayed_eval = traj.reward_per_interval(evaluation=True)
        with open(d / "controller" / "metrics.csv", newline="") as f:
            reported = list(csv.DictReader(f))
        assert sorted(replayed) == [int(r["interval"]) for r in reported]
        for r in reported:
            k = int(r["interval"])
            # Exact: the same rewards of the same published levels, averaged in
            # the same order; compared at the precision the controller wrote.
            assert _same(replayed[k], r["reward_per_step"]), (spec.key, k)
            if r["eval_reward_per_step"]:
                assert _same(replayed_eval[k], r["eval_reward_per_step"]), (spec.key, k)
        # 64 operating steps per interval, as many rows as the controller took.
        assert int((~traj.evaluation).sum()) == 2 * 64


def _same(value: float, written: str) -> bool:
    return value == float(written) or f"{value:.6g}" == written


def test_parallel_runs_never_receive_each_others_messages(all_run):
    results = [json.loads(p.read_text()) for p in all_run.glob("runs/**/result.json")]
    assert len({r["lcm_url"] for r in results}) == len(results)
    assert len({r["prefix"] for r in results}) == len(results)
    # Runs did overlap in time (2 jobs), so isolation was actually exercised.
    spans = sorted((r["started"], r["finished"]) for r in results)
    assert any(b[0] < a[1] for a, b in zip(spans, spans[1:]))
    for r in results:
        log = all_run / "runs" / r["run"] / "plant.lcmlog"
        import lcm

        channels = set()
        for event in lcm.EventLog(str(log), "r"):
            channels.add(event.channel)
        assert channels and all(c.startswith(r["prefix"]) for c in channels), channels
        traj = read_log(log)
        ops = traj.operating_steps[~traj.evaluation]
        # One plant's history: operating steps count up by one, never interleaved.
        assert np.array_equal(ops, np.arange(1, len(ops) + 1))


def test_two_plants_on_private_urls_do_not_hear_each_other():
    import lcm

    from ftc.plant import launch, private_lcm_url, private_prefix

    urls = [private_lcm_url(), private_lcm_url()]
    while urls[0] == urls[1]:
        urls[1] = private_lcm_url()
    heard: list[list[str]] = [[], []]
    spies = [lcm.LCM(u) for u in urls]
    for i, spy in enumerate(spies):
        spy.subscribe(".*", lambda ch, data, i=i: heard[i].append(ch))
    prefixes = [private_prefix(), private_prefix()]
    with launch(None, 0, lcm_url=urls[0], prefix=prefixes[0]) as a, \
            launch(None, 0, lcm_url=urls[1], prefix=prefixes[1]) as b:
        for plant in (a, b):
            plant.reset()
        for _ in range(20):
            a.step(np.zeros(6, dtype=np.int8))
            b.step(np.ones(6, dtype=np.int8))
            for spy in spies:
                while spy.handle_timeout(0):
                    pass
    for i in range(2):
        assert heard[i], "the spy should hear its own plant"
        # LCM_SELF_TEST: what each LCM instance publishes to itself on start.
        assert all(ch.startswith(prefixes[i]) for ch in heard[i] if ch != "LCM_SELF_TEST"), \
            set(heard[i])


def _tree_digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def test_resume_after_kill_completes_and_keeps_finished_runs(tmp_path):
    out = tmp_path / "resume"
    args = ["single", "--out", str(out), "--methods", "closed", "open", "--seeds", "0", "1",
            "--intervals", "2", "--steps-per-interval", "128", "--jobs", "1"]
    proc = subprocess.Popen([sys.executable, "-m", "ftc.experiments", *args],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    first = out / "runs" / "single" / "t00" / "closed" / "s0"
    second = out / "runs" / "single" / "t00" / "closed" / "s1"
    deadline = time.monotonic() + 120
    # Wait for an observable state (first run finished, second one's controller
    # started), then kill the orchestrator outright.
    while not (ex.is_finished(first) and "controller" in _processes(second)):
        assert proc.poll() is None, proc.stderr.read().decode()[-2000:]
        assert time.monotonic() < deadline, "runs did not start in time"
        time.sleep(0.05)
    proc.kill()
    proc.wait()
    assert not ex.is_finished(second)
    before = _tree_digest(first)
    done = _run_cli(["--resume", *args])
    assert done.returncode == 0, done.stderr[-3000:]
    assert "1 already finished" in done.stderr
    assert _tree_digest(first) == before
    for method in ("closed", "open"):
        for seed in (0, 1):
            assert ex.is_finished(out / "runs" / "single" / "t00" / method / f"s{seed}")
    assert not (second / "processes.json").exists()


def _processes(run_dir: Path) -> dict:
    try:
        return json.loads((run_dir / "processes.json").read_text())
    except (OSError, ValueError):
        return {}


# ---------------------------------------------------------------------------
# Saved fixture results: figures and report, no plant needed
# ---------------------------------------------------------------------------

@pytest.fixture
def fixture_run(tmp_path) -> Path:
    run = tmp_path / "fixture"
    shutil.copytree(FIXTURE, run)
    return run


def test_each_figure_function_draws_from_saved_results(fixture_run, tmp_path):
    out = tmp_path / "figs"
    a = figures.reward_episodes(
        [("nominal", "closed", fixture_run / "baselines" / "nominal-closed.csv"),
         ("nominal", "open", fixture_run / "baselines" / "nominal-open.csv"),
         ("degraded", "closed", fixture_run / "baselines" / "multiple-age1-closed.csv")],
        out / "a")
    b = figures.reward_per_interval(fixture_run / "results.csv", out / "b")
    c = figures.tank_control([("single", fixture_run / "trajectories" / "single-tank-control.csv"),
                              ("multiple",
                               fixture_run / "trajectories" / "multiple-tank-control.csv")],
                             out / "c")
    d = figures.aggregate(fixture_run / "results.csv", out / "d")
    for paths in (a, b, c, d):
        assert [p.suffix for p in paths] == [".png", ".svg"]
        assert all(p.stat().st_size > 1000 for p in paths)


def test_report_from_saved_results(fixture_run):
    md, page = report.write_report(fixture_run)
    text = md.read_text()
    assert "| method | 0 | 1 | mean |" in text
    assert "all valves closed" in text and "aggregate-01" in text
    assert "figures/c_tank_control.png" in text
    assert "data:image/png;base64," in page.read_text()


def test_figure_reads_only_saved_values(fixture_run, tmp_path):
    # Changing a saved value changes the figure: the plot does not recompute it.
    # Compared as pixels: SVG output carries a date and salted element ids, so
    # two SVG renders of the same data differ byte for byte.
    import matplotlib.image

    res = fixture_run / "results.csv"

    def pixels(name: str) -> np.ndarray:
        png = figures.reward_per_interval(res, tmp_path / name, formats=("png",))[0]
        return matplotlib.image.imread(png)

    first = pixels("one")
    assert np.array_equal(first, pixels("again"))  # the same saved data, the same figure
    text = res.read_text().splitlines()
    header = text[0].split(",")
    col = header.index("reward_per_step")
    cells = text[1].split(",")
    cells[col] = "0.123"
    res.write_text("\n".join([text[0], ",".join(cells), *text[2:]]) + "\n")
    second = pixels("two")
    assert first.shape != second.shape or not np.array_equal(first, second)


# ---------------------------------------------------------------------------
# Scenarios, replay errors
# ---------------------------------------------------------------------------

def test_aggregate_scenarios_are_drawn_from_the_recorded_seed():
    a, b = ex.aggregate_scenarios(20, 7), ex.aggregate_scenarios(20, 7)
    assert a == b and a != ex.aggregate_scenarios(20, 8)
    for sc in a:
        tanks = [v for v in sc.tank_factor if not math.isinf(v)]
        engines = [v for v in sc.engine_factor if not math.isinf(v)]
        assert len(tanks) == 1 and len(engines) == 1
        assert 10.0 <= tanks[0] <= 30.0 and 10.0 <= engines[0] <= 30.0
    assert len({sc.tank_factor.index(next(v for v in sc.tank_factor if not math.isinf(v)))
                for sc in a}) > 1
    toml = a[0].toml(512)
    assert "tank_factor = [" in toml and "inf" in toml and "steps_per_interval = 512" in toml


def test_unknown_method_is_refused():
    proc = _run_cli(["single", "--methods", "nonsense", "--out", "/nonexistent"])
    assert proc.returncode == 2 and "unknown methods" in proc.stderr


def test_replay_summary_and_truncated_log_error(tmp_path, write_state_log):
    good = tmp_path / "good.lcmlog"
    write_state_log(good, 5)
    traj = read_log(good)
    assert len(traj) == 5 and traj.reward_per_interval()[0] == pytest.approx(
        float(np.mean(traj.reward)))
    data = good.read_bytes()
    cut = tmp_path / "cut.lcmlog"
    cut.write_bytes(data[:len(data) - 40])
    proc = subprocess.run([sys.executable, "-m", "ftc.replay", str(cut)], capture_output=True,
                          text=True)
    assert proc.returncode == 2
    assert str(cut) in proc.stderr and "byte offset" in proc.stderr
    import lcm

    log = lcm.EventLog(str(good), "r")
    log.read_next_event()
    second_event = log.tell()
    log.close()
    garbage = tmp_path / "garbage.lcmlog"  # the second event's sync word overwritten
    garbage.write_bytes(data[:second_event] + b"\xff" * 4 + data[second_event + 4:])
    with pytest.raises(LogError, match="byte offset"):
        read_log(garbage)


def test_model_search_quick_ranks_the_grid_into_the_report(fixture_run):
    from ftc.experiments.model_search import model_search  # the function, not the module

    results = model_search(fixture_run, ex.QUICK_MODEL_SEARCH, jobs=1)
    assert [r["rank"] for r in results] == [1, 2]
    assert results[0]["r2_mean"] >= results[1]["r2_mean"] > 0.9
    assert len(ex.ModelSearchConfig().grid()) == 5 * 2 * 2 * 3  # the paper's grid
    report.write_report(fixture_run)
    text = (fixture_run / "report.md").read_text()
    assert "World-model search" in text and "| 1 | 2 x 32 |" in text
