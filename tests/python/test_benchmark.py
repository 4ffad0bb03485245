"""The benchmark suite: the default scenarios' generator, the command line's
checks, and a reduced suite end to end (2 scenarios, closed / balance /
oracle-mpc as the reference, 2 seeds, 2 intervals of 64 steps, --link core, --jobs 2):
results.csv, the normalized scores (closed 0, the reference 1, one checked by
hand) and the fractions of the oracle checked by hand, the report's summary
lines, the figure, and --resume skipping finished runs; the normalized
score's formula on its own, and a quick run with another --reference.

Quality is measured by the benchmark itself, not here: this checks the pipeline.
"""

from __future__ import annotations

import csv
import json
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ftc import _core
from ftc.experiments import benchmark, benchmark_report, suite
from ftc.experiments.methods import METHODS

SHORT = ["--intervals", "2", "--steps-per-interval", "64", "--jobs", "2"]
METHODS_RUN = ("closed", "balance", "oracle-mpc")
SEEDS = (0, 1)


def _run_cli(args: list[str], timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ftc.experiments", "benchmark", *args],
                          capture_output=True, text=True, timeout=timeout)


# ---------------------------------------------------------------------------
# The generator
# ---------------------------------------------------------------------------

def test_the_random_scenarios_are_fixed_and_drawn_as_specified(tmp_path):
    a, b = suite.write_suite(tmp_path / "a"), suite.write_suite(tmp_path / "b")
    assert [p.name for p in a] == [p.name for p in b]
    assert [p.read_bytes() for p in a] == [p.read_bytes() for p in b]
    assert [p.stem for p in a[:2]] == ["single", "multiple"] and len(a) == 22
    randoms = suite.random_scenarios()
    assert len(randoms) == 20 and [s.name for s in randoms] == [p.stem for p in a[2:]]
    left_tank = right_tank = dead_pump = False
    for sc in randoms:
        tanks = [i for i, v in enumerate(sc.tank_factor) if math.isfinite(v)]
        engines = [j for j, v in enumerate(sc.engine_factor) if math.isfinite(v)]
        assert len(tanks) in (1, 2) and len(engines) in (1, 2), sc
        for v in [sc.tank_factor[i] for i in tanks] + [sc.engine_factor[j] for j in engines]:
            assert 6.0 <= v <= 30.0, sc
        left_tank |= any(i < 3 for i in tanks)
        right_tank |= any(i >= 3 for i in tanks)
        dead_pump |= any(sc.tank_factor[i] <= 9 for i in tanks)  # p(9) = 0 for D_T <= 9
    assert left_tank and right_tank and dead_pump
    n_engines = {sum(map(math.isfinite, sc.engine_factor)) for sc in randoms}
    n_tanks = {sum(map(math.isfinite, sc.tank_factor)) for sc in randoms}
    assert n_engines == {1, 2} and n_tanks == {1, 2}
    # The plant reads every file; single and multiple are the repository's.
    for p in a:
        loaded = _core.load_scenario(str(p))
        assert loaded.name == p.stem and loaded.steps_per_interval == 512
    for name in ("single", "multiple"):
        ours = _core.load_scenario(str(tmp_path / "a" / f"{name}.toml"))
        repo = _core.load_scenario(str(Path(__file__).parents[2] / "scenarios" / f"{name}.toml"))
        assert ours.tank_factor == repo.tank_factor and ours.engine_factor == repo.engine_factor


def test_another_seed_draws_other_scenarios():
    other = suite.random_scenarios(suite.SuiteConfig(seed=7))
    assert [s.tank_factor for s in other] != [s.tank_factor for s in suite.random_scenarios()]


# ---------------------------------------------------------------------------
# The command line: one-line errors, exit 2, nothing written
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("extra, message", [
    (["--methods", "closed", "nosuch"], "--methods: unknown methods ['nosuch']"),
    (["--scenarios", "missing.toml"], "cannot open the scenario file"),
    (["--seeds", "-1"], "argument --seeds"),
    (["--jobs", "0"], "argument --jobs"),
    (["--intervals", "0"], "argument --intervals"),
    (["--steps-per-interval", "64"], "multiple of --update-every"),
    (["--link", "udp"], "argument --link"),
    (["--controller-args", "--no-such-option 1"], "--no-such-option"),
    (["--reference", "nosuch"], "--reference: unknown method 'nosuch'"),
    (["--reference", "closed"], "--reference: closed is the normalized score's 0"),
])
def test_bad_input_is_one_line_exit_2_and_writes_nothing(tmp_path, capsys, extra, message):
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as e:
        benchmark.parse_args(["--out", str(out), *extra])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("ftc.experiments benchmark: error:")
    assert message in err[0], err
    assert not out.exists()


def test_a_malformed_scenario_and_two_files_of_one_stem_are_refused(tmp_path, capsys, scenarios):
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "bad"\ntank_factor = [1, 2]\n')
    (tmp_path / "d").mkdir()
    same = tmp_path / "d" / "single.toml"
    same.write_text((scenarios / "single.toml").read_text())
    for files, message in (([bad], "expected 6 numbers"),
                           ([scenarios / "single.toml", same], "two files named single")):
        with pytest.raises(SystemExit) as e:
            benchmark.parse_args(["--out", str(tmp_path / "out"), "--scenarios", *map(str, files)])
        assert e.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_defaults_every_benchmark_method_and_the_reference_always(tmp_path):
    args = benchmark.parse_args(["--out", str(tmp_path / "o")])
    assert args.config.methods == benchmark.default_methods()
    assert set(args.config.methods) == {m for m, s in METHODS.items() if s.benchmark}
    assert args.config.seeds == (0, 1, 2) and args.config.link == "core"
    assert list(args.texts) == [s.name for s in suite.default_suite()]
    assert args.config.reference == "reference" and "oracle-mpc" in args.config.methods
    args = benchmark.parse_args(["--out", str(tmp_path / "o"), "--methods", "closed"])
    assert args.config.methods == ("closed", "reference")
    args = benchmark.parse_args(["--out", str(tmp_path / "o"), "--methods", "balance"])
    assert args.config.methods == ("balance", "reference", "closed")
    args = benchmark.parse_args(["--out", str(tmp_path / "o"), "--methods", "open",
                                 "--reference", "balance"])
    assert args.config.methods == ("open", "balance", "closed")
    assert args.config.reference == "balance"
    assert not (tmp_path / "o").exists()


# ---------------------------------------------------------------------------
# The normalized score on its own
# ---------------------------------------------------------------------------

def test_the_normalized_score_is_0_for_closed_1_for_the_reference_and_undefined_on_a_tie():
    score = benchmark_report.normalized_score
    assert score(1.5, 2.0, 1.0) == 0.5 and score(0.5, 2.0, 1.0) == -0.5
    assert score(1.0, 2.0, 1.0) == 0.0 and score(2.0, 2.0, 1.0) == 1.0
    assert score(2.5, 2.0, 1.0) == 1.5  # better than the reference
    assert score(1.7, 1.7, 1.7) is None  # reference == closed: no spread to measure in
    assert score(None, 2.0, 1.0) is None and score(1.5, None, 1.0) is None \
        and score(1.5, 2.0, None) is None
    zero = score(1.0, 0.9, 1.0)  # a reference below closed: closed is +0, not -0
    assert zero == 0.0 and math.copysign(1.0, zero) == 1.0
    rows = [{"scenario": "a", "method": m, "seed": 0, "interval": k, "reward_per_step": v}
            for k, values in ((0, {"closed": 2.4, "ref": 2.4, "x": 2.0}),
                              (1, {"closed": 1.0, "ref": 2.0, "x": 1.25}))
            for m, v in values.items()]
    rows.append({"scenario": "a", "method": "x", "seed": 1, "interval": 1, "reward_per_step": 1.1})
    out = {(r["method"], r["seed"], r["interval"]): r
           for r in benchmark_report.normalized_scores(rows, "ref")}
    assert [out[("x", 0, k)]["normalized_score"] for k in (0, 1)] == [None, 0.25]
    assert out[("closed", 0, 1)]["normalized_score"] == 0.0
    assert out[("ref", 0, 1)]["normalized_score"] == 1.0
    assert out[("ref", 0, 0)]["normalized_score"] is None  # the tie: every method's cell
    assert (out[("x", 0, 1)]["reference_reward_per_step"],
            out[("x", 0, 1)]["closed_reward_per_step"]) == (2.0, 1.0)
    missing = out[("x", 1, 1)]  # seed 1 has no reference or closed run
    assert missing["normalized_score"] is None and missing["reference_reward_per_step"] is None
    assert rows[0].keys() == {"scenario", "method", "seed", "interval", "reward_per_step"}


# ---------------------------------------------------------------------------
# A reduced suite end to end
# ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def bench(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("bench")
    generated = suite.write_suite(root / "suite", steps_per_interval=64)
    files = [generated[2], Path(__file__).parents[2] / "scenarios" / "single.toml"]
    out = root / "out"
    proc = _run_cli(["--scenarios", *map(str, files), "--methods", *METHODS_RUN,
                     "--seeds", *map(str, SEEDS), "--link", "core", "--reference", "oracle-mpc",
                     "--out", str(out), *SHORT])
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out


def _results(out: Path) -> list[dict]:
    with open(out / "results.csv", newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.quick  # the fast tier's integration of this boundary
def test_results_csv_has_every_run_and_interval(bench):
    rows = _results(bench)
    header = list(rows[0])
    assert header[:5] == ["scenario", "method", "seed", "interval", "reward_per_step"]
    assert "eval_reward_per_step" in header and "episodes" in header
    assert {"reference_reward_per_step", "closed_reward_per_step", "normalized_score"} <= set(
        header)
    assert len(rows) == 2 * len(METHODS_RUN) * len(SEEDS) * 2
    assert {r["scenario"] for r in rows} == {"random-00", "single"}
    assert {(r["method"], r["seed"], r["interval"]) for r in rows} == {
        (m, str(s), str(k)) for m in METHODS_RUN for s in SEEDS for k in (0, 1)}
    meta = json.loads((bench / "benchmark.json").read_text())
    assert meta["config"]["link"] == "core" and meta["config"]["scenarios"] == ["random-00",
                                                                              "single"]
    assert meta["config"]["reference"] == "oracle-mpc"
    assert (bench / "scenarios" / "random-00.toml").is_file()
    # link core: no plant process and no recorder
    run = bench / "runs" / "single" / "t00" / "closed" / "s0"
    assert (run / "result.json").is_file() and not (run / "plant.lcmlog").exists()


def _cell(rows: list[dict], scenario: str, method: str, seed: int, interval: int) -> float:
    return next(float(r["reward_per_step"]) for r in rows if (r["scenario"], r["method"],
                r["seed"], r["interval"]) == (scenario, method, str(seed), str(interval)))


def _value(rows: list[dict], column: str, scenario: str, method: str, seed: int,
           interval: int) -> str:
    return next(r[column] for r in rows if (r["scenario"], r["method"], r["seed"],
                r["interval"]) == (scenario, method, str(seed), str(interval)))


def test_closed_scores_0_and_the_reference_1_in_every_cell_with_a_score(bench):
    rows = _results(bench)
    cells = {(r["scenario"], r["seed"], r["interval"]) for r in rows}
    scored = 0
    for sc, s, k in cells:
        here = {r["method"]: r for r in rows if (r["scenario"], r["seed"], r["interval"])
                == (sc, s, k)}
        ref, closed = here["oracle-mpc"]["reward_per_step"], here["closed"]["reward_per_step"]
        for r in here.values():  # every row of a cell carries the cell's two rewards
            assert (r["reference_reward_per_step"], r["closed_reward_per_step"]) == (ref, closed)
        if float(ref) == float(closed):  # undefined: empty for every method
            assert all(r["normalized_score"] == "" for r in here.values())
            continue
        scored += 1
        assert float(here["closed"]["normalized_score"]) == 0.0
        assert float(here["oracle-mpc"]["normalized_score"]) == 1.0
        assert here["balance"]["normalized_score"] != ""
    # interval 1, after the faults grew, separates closed from the oracle everywhere
    assert scored >= len(cells) // 2
    assert all(float(_value(rows, "reward_per_step", sc, "closed", s, 1))
               != float(_value(rows, "reward_per_step", sc, "oracle-mpc", s, 1))
               for sc in ("random-00", "single") for s in SEEDS)


def test_a_normalized_score_by_hand(bench):
    rows = _results(bench)
    r, closed, ref = (_cell(rows, "single", m, 1, 1) for m in ("balance", "closed", "oracle-mpc"))
    assert float(_value(rows, "normalized_score", "single", "balance", 1, 1)) == pytest.approx(
        (r - closed) / (ref - closed), rel=1e-12)
    assert float(_value(rows, "reference_reward_per_step", "single", "balance", 1, 1)) == ref
    assert float(_value(rows, "closed_reward_per_step", "single", "balance", 1, 1)) == closed
    results = json.loads((bench / "results.json").read_text())["metrics"]
    assert [m["normalized_score"] for m in results] == [
        None if x["normalized_score"] == "" else float(x["normalized_score"]) for x in rows]


def test_fractions_are_the_ratio_to_the_oracle(bench):
    rows = _results(bench)
    fractions = benchmark_report.read_fractions(bench / "fractions.csv")
    assert len(fractions) == len(rows)
    assert all(f["fraction"] == 1.0 for f in fractions if f["method"] == "oracle-mpc")
    cell = next(f for f in fractions if (f["scenario"], f["method"], f["seed"], f["interval"])
                == ("single", "closed", 1, 1))
    by_hand = _cell(rows, "single", "closed", 1, 1) / _cell(rows, "single", "oracle-mpc", 1, 1)
    assert cell["fraction"] == pytest.approx(by_hand, rel=1e-12)
    assert 0.5 < by_hand < 1.0  # closed falls behind once the engine has degraded


def _table_row(report: str, second_header: str, method: str) -> list[str]:
    """The cells of ``method``'s row in the report's table whose second header is
    ``second_header``."""
    lines = report.splitlines()
    start = next(i for i, x in enumerate(lines) if x.startswith(f"| method | {second_header} |"))
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        if line.startswith(f"| {method} ("):
            return [c.strip() for c in line.strip("|").split("|")]
    raise AssertionError(f"no row {method} in the table of {second_header}")


def _summary(values: dict) -> dict[str, str]:
    """What the report prints of {(scenario, seed, interval): value} (None: no value)."""
    f = {key: v for key, v in values.items() if v is not None}
    per_interval = {k: np.mean([v for key, v in f.items() if key[2] == k]) for k in (0, 1)
                    if any(key[2] == k for key in f)}
    per_seed = {s: np.mean([v for key, v in f.items() if key[1] == s]) for s in SEEDS}
    per_scenario = {sc: np.mean([v for key, v in f.items() if key[0] == sc])
                    for sc in ("random-00", "single")}
    per_cell = {(a, b): np.mean([v for key, v in f.items() if (key[0], key[2]) == (a, b)])
                for a in ("random-00", "single") for b in (0, 1)
                if any((key[0], key[2]) == (a, b) for key in f)}
    k = min(per_interval, key=lambda j: (per_interval[j], str(j)))
    s = min(per_seed, key=lambda j: (per_seed[j], str(j)))
    sc = min(per_scenario, key=lambda j: (per_scenario[j], j))
    c = min(per_cell, key=lambda j: (per_cell[j], str(j)))
    return {"mean": f"{np.mean(list(f.values())):.3f}",
            "worst interval": f"{per_interval[k]:.3f} (interval {k})",
            "worst seed": f"{per_seed[s]:.3f} (seed {s})",
            "worst scenario": f"{per_scenario[sc]:.3f} ({sc})",
            "worst scenario-interval": f"{per_cell[c]:.3f} ({c[0]}, interval {c[1]})",
            "cells": str(len(f))}


def test_the_report_leads_with_the_score_and_names_the_worst_interval_seed_and_scenario(bench):
    rows = _results(bench)
    report = (bench / "report.md").read_text()
    assert report.index("## Normalized score") < report.index("## Fraction of the oracle")
    keys = [(sc, s, k) for sc in ("random-00", "single") for s in SEEDS for k in (0, 1)]
    for method in ("closed", "balance"):
        fraction = _summary({key: _cell(rows, key[0], method, *key[1:])
                             / _cell(rows, key[0], "oracle-mpc", *key[1:]) for key in keys})
        score = {}
        for key in keys:
            r, c, o = (_cell(rows, key[0], m, *key[1:]) for m in (method, "closed",
                                                                   "oracle-mpc"))
            score[key] = None if o == c else (r - c) / (o - c) + 0.0  # no -0.0
        score = _summary(score)
        lead = _table_row(report, "normalized score", method)
        assert lead[1:3] == [score["mean"], fraction["mean"]]
        assert lead[3:] == [score[k] for k in ("worst interval", "worst seed", "worst scenario",
                                               "worst scenario-interval", "cells")]
        cells = _table_row(report, "mean fraction", method)
        assert cells[1:] == [fraction[k] for k in ("mean", "worst interval", "worst seed",
                                                   "worst scenario", "worst scenario-interval",
                                                   "cells")]
    assert _table_row(report, "normalized score", "oracle-mpc")[1:3] == ["1.000", "1.000"]
    assert _table_row(report, "normalized score", "closed")[1] == "0.000"
    assert _table_row(report, "mean fraction", "oracle-mpc")[1] == "1.000"
    tied = sum(1 for sc, s, k in keys if _cell(rows, sc, "closed", s, k)
               == _cell(rows, sc, "oracle-mpc", s, k))
    if tied:
        assert (f"{tied} of {len(keys)} (scenario, seed, interval) cells have no score: {tied} "
                "where the reference earns exactly what closed earns, 0 where") in report
    else:
        assert "cells have no score" not in report
    assert "### single: engine E1 D_E=20.00" in report
    # per-scenario table: closed's score per interval (empty where tied), its mean and
    # its mean fraction
    assert re.search(r"\| closed \| (0\.000)? \| 0\.000 \| 0\.000 \| (1\.000|0\.\d{3}) \|",
                     report)


def test_the_figure_is_a_png_linked_in_the_report(bench):
    png = bench / "figures" / "benchmark_score.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "(figures/benchmark_score.png)" in (bench / "report.md").read_text()
    assert "data:image/png;base64," in (bench / "report.html").read_text()


def test_resume_skips_finished_runs_and_redoes_the_rest(bench):
    results = sorted((bench / "runs").rglob("result.json"))
    assert len(results) == 2 * len(METHODS_RUN) * len(SEEDS)
    stamps = {p: p.stat().st_mtime_ns for p in results}
    proc = _run_cli(["--out", str(bench), "--resume", "--jobs", "2"])
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "(12 already finished)" in proc.stderr
    assert {p: p.stat().st_mtime_ns for p in results} == stamps
    redo = bench / "runs" / "random-00" / "t00" / "balance" / "s1" / "result.json"
    before = _results(bench)
    redo.unlink()
    proc = _run_cli(["--out", str(bench), "--resume", "--jobs", "2"])
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "(11 already finished)" in proc.stderr
    assert all(p.stat().st_mtime_ns == t for p, t in stamps.items() if p != redo)
    after = _results(bench)
    key = ("scenario", "method", "seed", "interval", "reward_per_step")
    assert [[r[k] for k in key] for r in after] == [[r[k] for k in key] for r in before]
    # A finished directory is not started over by mistake.
    proc = _run_cli(["--out", str(bench)])
    assert proc.returncode == 2 and "already holds a benchmark" in proc.stderr
    proc = _run_cli(["--out", str(bench), "--resume", "--intervals", "3"])
    assert proc.returncode == 2 and "--intervals differs" in proc.stderr


@pytest.mark.slow  # 10-30 s: the fresh-clone CI stays under its 10 minutes
def test_another_reference_is_recorded_and_a_resume_with_a_different_one_refused(tmp_path):
    out = tmp_path / "quick"
    single = Path(__file__).parents[2] / "scenarios" / "single.toml"
    proc = _run_cli(["--scenarios", str(single), "--methods", "balance", "--reference",
                     "balance", "--seeds", "0", "--out", str(out), *SHORT])
    assert proc.returncode == 0, proc.stderr[-3000:]
    meta = json.loads((out / "benchmark.json").read_text())
    assert meta["config"]["reference"] == "balance"
    assert meta["config"]["methods"] == ["balance", "closed"]  # no oracle-mpc: a quick run
    rows = _results(out)
    assert {r["method"] for r in rows} == {"balance", "closed"} and len(rows) == 4
    for r in rows:
        if r["reference_reward_per_step"] != r["closed_reward_per_step"]:
            assert float(r["normalized_score"]) == (1.0 if r["method"] == "balance" else 0.0)
    assert all(f["fraction"] is None for f in benchmark_report.read_fractions(
        out / "fractions.csv"))  # the fraction is of oracle-mpc, which did not run
    report = (out / "report.md").read_text()
    assert "| balance (rule: balance the wings) | 1.000 |  |" in report
    before = (out / "benchmark.json").read_bytes()
    for other in ("oracle-mpc", "open"):
        proc = _run_cli(["--out", str(out), "--resume", "--reference", other])
        err = proc.stderr.strip().splitlines()
        assert proc.returncode == 2 and len(err) == 1, proc.stderr
        assert err[0] == (f"ftc.experiments benchmark: error: --resume: --reference differs "
                          f"from the stored balance of {out / 'benchmark.json'}")
    assert (out / "benchmark.json").read_bytes() == before
    proc = _run_cli(["--out", str(out), "--resume", "--reference", "balance"])
    assert proc.returncode == 0 and "(2 already finished)" in proc.stderr, proc.stderr[-2000:]
