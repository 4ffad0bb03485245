"""scripts/suite_results.py: benchmark directories -> the committed result file
the docs' suite tables are rendered from (scripts/render_results.py)."""

from __future__ import annotations

import csv
import importlib.util
import json
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def _script(name: str):
    spec = importlib.util.spec_from_file_location(name, REPO / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _bench(path: Path, rewards: dict[str, list[float]], reference: str = "oracle-mpc") -> Path:
    """A benchmark directory of one scenario, seed 0, an interval per reward."""
    path.mkdir()
    with open(path / "results.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["scenario", "method", "seed", "interval", "reward_per_step"])
        for method, values in rewards.items():
            for k, v in enumerate(values):
                w.writerow(["s", method, 0, k, v])
    (path / "benchmark.json").write_text(json.dumps({
        "config": {"scenarios": ["s"], "methods": list(rewards), "seeds": [0],
                   "intervals": 2, "steps_per_interval": 8, "reference": reference},
        "methods": {m: {"label": m.upper()} for m in rewards},
        "git_revision": "abc", "created": "2026-01-02T03:04:05", "jobs": 2, "wall_time_s": 7}))
    return path


def _rows(path: Path) -> dict[str, dict]:
    lines = [line for line in path.read_text().splitlines() if not line.startswith("#")]
    return {r["method"]: r for r in csv.DictReader(lines)}


def test_scores_and_fractions_have_their_known_values(tmp_path):
    # interval 1: closed 1.0, oracle 2.0, balance 1.5 -> score 0.5, fraction 0.75;
    # interval 0: closed == oracle, so no score (the cell count says 1)
    bench = _bench(tmp_path / "b", {"closed": [2.0, 1.0], "oracle-mpc": [2.0, 2.0],
                                    "balance": [1.9, 1.5]})
    out = tmp_path / "suite.csv"
    assert _script("suite_results").main([str(bench), "--out", str(out)]) == 0
    rows = _rows(out)
    assert rows["balance"]["normalized score"] == "0.500"
    assert rows["balance"]["cells"] == "1"
    assert rows["balance"]["score_0"] == "" and rows["balance"]["score_1"] == "0.500"
    assert rows["balance"]["fraction_0"] == "0.950" and rows["balance"]["fraction_1"] == "0.750"
    assert rows["oracle-mpc"]["normalized score"] == "1.000"
    assert "# commit: abc" in out.read_text()


def test_a_reference_run_apart_rebases_the_others(tmp_path):
    # the reference (3.0 in interval 1) comes from its own directory
    main = _bench(tmp_path / "main", {"closed": [2.0, 1.0], "oracle-mpc": [2.0, 2.0]})
    ref = _bench(tmp_path / "ref", {"closed": [2.0, 1.0], "reference": [2.5, 3.0]},
                 reference="reference")
    out = tmp_path / "suite.csv"
    _script("suite_results").main([str(main), str(ref), "--out", str(out),
                                   "--reference", "reference"])
    assert _rows(out)["oracle-mpc"]["score_1"] == "0.500"  # (2 - 1) / (3 - 1)


def test_a_cell_given_twice_differently_writes_nothing(tmp_path):
    a = _bench(tmp_path / "a", {"closed": [2.0, 1.0], "oracle-mpc": [2.0, 2.0]})
    b = _bench(tmp_path / "b", {"closed": [2.0, 1.1], "oracle-mpc": [2.0, 2.0]})
    out = tmp_path / "suite.csv"
    with pytest.raises(SystemExit, match=r"given twice with different rewards"):
        _script("suite_results").main([str(a), str(b), "--out", str(out)])
    assert not out.exists()


def test_a_directory_without_results_is_named(tmp_path):
    with pytest.raises(SystemExit, match=r"holds no benchmark results"):
        _script("suite_results").main([str(tmp_path), "--out", str(tmp_path / "x.csv")])
