"""scripts/headroom.py: the volume bound by hand, the margins it reads from a
benchmark directory, a method above the reference named, and a reference
below the oracle refused with nothing written."""

from __future__ import annotations

import csv
import math
import sys
from pathlib import Path

import pytest

from bench_dirs import REPO, write_benchmark

sys.path.insert(0, str(REPO / "scripts"))

import headroom  # noqa: E402


def test_the_most_outward_balanced_spread_by_hand():
    assert headroom.sigma_max(6.0) == pytest.approx(math.sqrt(14 / 3))  # full tanks
    assert headroom.sigma_max(1.0) == pytest.approx(3.0)  # all in the two outer tanks
    # 3 m^3: both outer tanks full, 0.5 in each of the next: (2*9 + 1*4) / 3
    assert headroom.sigma_max(3.0) == pytest.approx(math.sqrt(22 / 3))
    assert headroom.sigma_max(0.0) == 0.0


def test_the_volume_bound_follows_the_episodes_sawtooth():
    # 3 m^3 a step from 6: one step to 3 m^3, which ends the episode (3 < 3 + 1e-6)
    assert headroom.volume_bound(3.0, 4) == pytest.approx(math.sqrt(22 / 3))
    # 2 m^3 a step: 4 (then 2: below 2 + 1e-6? no, 2 < 2.000001: it ends) -> 4, 2, 4, 2
    expected = (headroom.sigma_max(4.0) + headroom.sigma_max(2.0)) / 2
    assert headroom.volume_bound(2.0, 4) == pytest.approx(expected)


def _benchmark(path: Path, rewards: dict[str, list[float]]) -> Path:
    """A finished benchmark directory of scenario 'single', seed 0."""
    return write_benchmark(path, {m: {("single", 0): v} for m, v in rewards.items()})


def test_margins_bound_and_methods_above_the_reference(tmp_path):
    oracle = [2.6 - 0.01 * k for k in range(10)]
    reference = [r * 1.02 for r in oracle]
    balance = list(reference)
    balance[4] = reference[4] * 1.001  # above the reference by 0.1%
    d = _benchmark(tmp_path / "b", {"reference": reference, "oracle-mpc": oracle,
                                    "closed": [2.5] * 10, "balance": balance})
    out = tmp_path / "headroom.csv"
    assert headroom.main([str(d), "--out", str(out), "--top", "2"]) == 0
    rows = list(csv.DictReader(line for line in out.read_text().splitlines()
                               if not line.startswith("#")))
    assert rows[0]["cells"] == "intervals 1-9, mean"
    assert rows[0]["reference over oracle-mpc"] == "+2.00%"
    # single's pumps carry their engine alone in every interval: a bound everywhere,
    # and above the reference (2.6 a step is below the healthy plant's 2.69)
    assert rows[0]["scenario-intervals"] == "9 (9 with a bound)"
    assert float(rows[0]["bound over reference"].rstrip("%")) > 0
    assert rows[-1]["reference over oracle-mpc"] == "1"
    assert rows[-1]["scenario-intervals"] == "balance in single interval 4"


def test_a_reference_below_the_oracle_is_refused_and_nothing_written(tmp_path, capsys):
    oracle = [2.6] * 10
    reference = list(oracle)
    reference[7] = 2.59
    d = _benchmark(tmp_path / "b", {"reference": reference, "oracle-mpc": oracle,
                                    "closed": [2.5] * 10})
    out = tmp_path / "headroom.csv"
    assert headroom.main([str(d), "--out", str(out)]) == 1
    assert "single interval 7" in capsys.readouterr().err and not out.exists()
