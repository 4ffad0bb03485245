"""ftc.experiments compare: entries named by method (and directory where several
hold one), scores rebased on a reference another directory holds, the paired
difference and its standard error by hand, and every incompatibility refused
in one line naming it, with nothing written."""

from __future__ import annotations

import contextlib
import csv
import io
from pathlib import Path

import numpy as np
import pytest

from bench_dirs import write_benchmark
from ftc.experiments import cli, compare

CLOSED = [2.0] * 4
REFERENCE = [2.0, 3.0, 3.0, 3.0]  # reference - closed = 1 from interval 1 on: score = r - 2


def _runs(values_by_seed: dict[int, list[float]], scenario: str = "single") -> dict:
    return {(scenario, seed): v for seed, v in values_by_seed.items()}


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture
def two_dirs(tmp_path):
    """A: closed, oracle-mpc and balance, scored against oracle-mpc; B: reference,
    closed and balance again (another commit, say), seeds 0 and 1 in both."""
    a = write_benchmark(tmp_path / "A", {
        "closed": _runs({0: CLOSED, 1: CLOSED}),
        "oracle-mpc": _runs({0: [2.0, 2.5, 2.5, 2.5], 1: [2.0, 2.5, 2.5, 2.5]}),
        "balance": _runs({0: [2.0, 2.4, 2.5, 2.6], 1: [2.0, 2.2, 2.3, 2.4]})},
        reference="oracle-mpc")
    b = write_benchmark(tmp_path / "B", {
        "reference": _runs({0: REFERENCE, 1: REFERENCE}),
        "closed": _runs({0: CLOSED, 1: CLOSED}),
        "balance": _runs({0: [2.0, 2.6, 2.7, 2.8], 1: [2.0, 2.3, 2.3, 2.3]})})
    return a, b


def test_entries_scores_and_the_paired_difference(two_dirs, tmp_path):
    a, b = two_dirs
    out = tmp_path / "cmp"
    # through the experiments' command line, as `python -m ftc.experiments compare`
    assert cli.main(["compare", str(a), str(b), "--reference", "reference",
                     "--out", str(out)]) == 0
    entries = {r["entry"]: r for r in _rows(out / "entries.csv")}
    assert set(entries) == {"closed@A", "closed@B", "oracle-mpc", "balance@A", "balance@B",
                            "reference"}
    # balance@A on A's own cells, rebased on B's reference: score = r - 2 (intervals 1-3)
    mean_a = np.mean([0.4, 0.5, 0.6, 0.2, 0.3, 0.4])
    assert float(entries["balance@A"]["normalized score"]) == pytest.approx(mean_a, abs=5e-4)
    assert entries["reference"]["normalized score"] == "1.000"
    pairs = {(r["entry"], r["against"]): r for r in _rows(out / "paired.csv")}
    p = pairs[("balance@B", "balance@A")]
    # per run (scenario, seed), the mean of B - A over intervals 1-3: seed 0 +0.2, seed 1 +0.0
    runs = np.array([0.2, 0.0])
    assert float(p["difference"]) == pytest.approx(runs.mean(), abs=1e-4)
    assert float(p["standard error"]) == pytest.approx(runs.std(ddof=1) / np.sqrt(2), abs=1e-3)
    assert (p["runs"], p["cells"]) == ("2", "6")
    report = (out / "compare.md").read_text()
    assert "Paired differences" in report and "balance@B" in report
    assert (out / "figures" / "benchmark_score.png").stat().st_size > 0


def test_against_pairs_every_entry_with_the_one_named(two_dirs, tmp_path):
    a, b = two_dirs
    out = tmp_path / "cmp"
    assert compare.main([str(a), str(b), "--reference", "reference", "--against",
                         "oracle-mpc", "--out", str(out)]) == 0
    against = {r["entry"] for r in _rows(out / "paired.csv") if r["against"] == "oracle-mpc"}
    assert {"balance@A", "balance@B", "reference"} <= against


def _refused(args: list[str], tmp_path: Path) -> str:
    """The one line (stderr) of an exit 2, in this process: the command line's
    parser exits before anything is written."""
    out = tmp_path / "refused"
    err = io.StringIO()
    with pytest.raises(SystemExit) as e, contextlib.redirect_stderr(err):
        compare.main([*args, "--out", str(out)])
    assert e.value.code == 2, err.getvalue()
    assert not out.exists()
    assert len(err.getvalue().strip().splitlines()) == 1, err.getvalue()
    return err.getvalue()


def test_incompatible_directories_are_refused_naming_the_difference(two_dirs, tmp_path):
    a, _ = two_dirs
    short = write_benchmark(tmp_path / "short", {"closed": _runs({0: CLOSED[:2]})})
    assert "has 2 intervals" in _refused([str(a), str(short)], tmp_path)
    steps = write_benchmark(tmp_path / "steps", {"closed": _runs({0: CLOSED})},
                            steps_per_interval=64)
    assert "64 steps per interval" in _refused([str(a), str(steps)], tmp_path)
    other = write_benchmark(tmp_path / "other", {"closed": _runs({0: CLOSED}, "multiple")})
    assert "different suites (scenario" in _refused([str(a), str(other)], tmp_path)
    edited = write_benchmark(tmp_path / "edited", {"closed": _runs({0: CLOSED})},
                             scenario_text={"single": "name = 'single'\n"})
    assert "scenario single differs" in _refused([str(a), str(edited)], tmp_path)
    assert "holds no finished benchmark" in _refused([str(a), str(tmp_path / "none")],
                                                     tmp_path)
    assert "--against nosuch: no such entry" in _refused(
        [str(a), "--against", "nosuch"], tmp_path)
    assert "is given twice" in _refused([str(a), str(a)], tmp_path)


def test_directories_of_one_name_are_told_apart_by_their_paths(tmp_path):
    runs = {"closed": {("single", 0): CLOSED}, "reference": {("single", 0): REFERENCE}}
    a = write_benchmark(tmp_path / "x" / "bench", runs)
    b = write_benchmark(tmp_path / "y" / "bench", runs)
    names = [n for n, _, _ in compare.entries([a, b], [compare.load(a)[1], compare.load(b)[1]])]
    assert f"closed@{a}" in names and f"closed@{b}" in names


def test_compare_prints_the_probability_of_improvement_with_its_interval(tmp_path, capsys):
    # score = mean over intervals 1-3 of r - 2 (REFERENCE - CLOSED = 1 there).
    # Scenario s1: B's balance runs 0.8, 0.9, A's 0.1, 0.2: B beats A in every pair.
    # Scenario s2: A's runs 0.5, 0.7, B's 0.6, 0.6: B wins 2 of 4 pairs -> 0.5.
    # P(B > A) = (1 + 0.5) / 2 = 0.75. Resampled, s1 stays 1 and s2 is 1 (A drew
    # 0.5, 0.5: 1 in 4), 0.5 (2 in 4) or 0 (0.7, 0.7: 1 in 4): the interval is [0.5, 1].
    def run(score):
        return [2.0] + [2.0 + score] * 3

    def both(scores_s1, scores_s2):
        return {**_runs({0: run(scores_s1[0]), 1: run(scores_s1[1])}, "s1"),
                **_runs({0: run(scores_s2[0]), 1: run(scores_s2[1])}, "s2")}

    fixed = {"reference": both((1.0, 1.0), (1.0, 1.0)), "closed": both((0.0, 0.0), (0.0, 0.0))}
    a = write_benchmark(tmp_path / "A", {**fixed, "balance": both((0.1, 0.2), (0.5, 0.7))})
    b = write_benchmark(tmp_path / "B", {**fixed, "balance": both((0.8, 0.9), (0.6, 0.6))})
    out = tmp_path / "cmp"
    assert compare.main([str(a), str(b), "--out", str(out)]) == 0
    printed = [line for line in capsys.readouterr().out.splitlines() if "P(" in line]
    assert printed == ["ftc.experiments compare: P(balance@B > balance@A) = 0.750 "
                       "[0.500, 1.000] over 2 scenarios"]
    found = {(r["entry"], r["against"]): r for r in _rows(out / "improvement.csv")}
    assert float(found[("balance@A", "balance@B")]["probability"]) == pytest.approx(0.25)
    # every pair of entries but the reference and closed: A's and B's balance
    assert set(found) == {("balance@A", "balance@B"), ("balance@B", "balance@A")}
    aggregates = {r["method"]: r for r in _rows(out / "aggregates.csv")}
    # IQM of B's 4 runs 0.6, 0.6, 0.8, 0.9: trim one each side -> (0.6 + 0.8) / 2
    assert float(aggregates["balance@B"]["IQM"]) == pytest.approx(0.7)
    assert "Probability of improvement" in (out / "compare.md").read_text()
