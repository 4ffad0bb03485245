"""The benchmark suite: the default scenarios' generator, the command line's
checks, and a reduced suite end to end (2 scenarios, closed / balance /
oracle-mpc, 2 seeds, 2 intervals of 64 steps, --link core, --jobs 2):
results.csv, the fractions of the oracle checked by hand, the report's
summary lines, the figure, and --resume skipping finished runs.

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


def test_defaults_every_benchmark_method_and_the_oracle_always(tmp_path):
    args = benchmark.parse_args(["--out", str(tmp_path / "o")])
    assert args.config.methods == benchmark.default_methods()
    assert set(args.config.methods) == {m for m, s in METHODS.items() if s.benchmark}
    assert args.config.seeds == (0, 1, 2) and args.config.link == "core"
    assert list(args.texts) == [s.name for s in suite.default_suite()]
    args = benchmark.parse_args(["--out", str(tmp_path / "o"), "--methods", "closed"])
    assert args.config.methods == ("closed", "oracle-mpc")
    assert not (tmp_path / "o").exists()


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
                     "--seeds", *map(str, SEEDS), "--link", "core", "--out", str(out), *SHORT])
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
    assert len(rows) == 2 * len(METHODS_RUN) * len(SEEDS) * 2
    assert {r["scenario"] for r in rows} == {"random-00", "single"}
    assert {(r["method"], r["seed"], r["interval"]) for r in rows} == {
        (m, str(s), str(k)) for m in METHODS_RUN for s in SEEDS for k in (0, 1)}
    meta = json.loads((bench / "benchmark.json").read_text())
    assert meta["config"]["link"] == "core" and meta["config"]["scenarios"] == ["random-00",
                                                                              "single"]
    assert (bench / "scenarios" / "random-00.toml").is_file()
    # link core: no plant process and no recorder
    run = bench / "runs" / "single" / "t00" / "closed" / "s0"
    assert (run / "result.json").is_file() and not (run / "plant.lcmlog").exists()


def _cell(rows: list[dict], scenario: str, method: str, seed: int, interval: int) -> float:
    return next(float(r["reward_per_step"]) for r in rows if (r["scenario"], r["method"],
                r["seed"], r["interval"]) == (scenario, method, str(seed), str(interval)))


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


def _summary_row(report: str, method: str) -> list[str]:
    line = next(x for x in report.splitlines() if x.startswith(f"| {method} (")
                and "(interval " in x)
    return [c.strip() for c in line.strip("|").split("|")]


def test_the_report_names_the_worst_interval_seed_and_scenario(bench):
    rows = _results(bench)
    report = (bench / "report.md").read_text()
    for method in ("closed", "balance"):
        f = {(sc, s, k): _cell(rows, sc, method, s, k) / _cell(rows, sc, "oracle-mpc", s, k)
             for sc in ("random-00", "single") for s in SEEDS for k in (0, 1)}
        per_interval = {k: np.mean([v for key, v in f.items() if key[2] == k]) for k in (0, 1)}
        per_seed = {s: np.mean([v for key, v in f.items() if key[1] == s]) for s in SEEDS}
        per_scenario = {sc: np.mean([v for key, v in f.items() if key[0] == sc])
                        for sc in ("random-00", "single")}
        k = min(per_interval, key=lambda j: (per_interval[j], str(j)))
        s = min(per_seed, key=lambda j: (per_seed[j], str(j)))
        sc = min(per_scenario, key=lambda j: (per_scenario[j], j))
        per_cell = {(a, b): np.mean([v for key, v in f.items() if (key[0], key[2]) == (a, b)])
                    for a in ("random-00", "single") for b in (0, 1)}
        c = min(per_cell, key=lambda j: (per_cell[j], str(j)))
        cells = _summary_row(report, method)
        assert cells[1] == f"{np.mean(list(f.values())):.3f}"
        assert cells[2] == f"{per_interval[k]:.3f} (interval {k})"
        assert cells[3] == f"{per_seed[s]:.3f} (seed {s})"
        assert cells[4] == f"{per_scenario[sc]:.3f} ({sc})"
        assert cells[5] == f"{per_cell[c]:.3f} ({c[0]}, interval {c[1]})"
    assert _summary_row(report, "oracle-mpc")[1] == "1.000"
    assert "### single: engine E1 D_E=20.00" in report
    assert re.search(r"\| closed \| 1\.000 \| 0\.\d{3} \|", report)  # per-scenario table


def test_the_figure_is_a_png_linked_in_the_report(bench):
    png = bench / "figures" / "benchmark_fraction.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "(figures/benchmark_fraction.png)" in (bench / "report.md").read_text()
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
