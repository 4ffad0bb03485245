"""ftc.experiments.tracks: each scenario's challenge axis read from the file the
plant parses, and its difficulty from the share of the reference's reward that
all valves closed gives up."""

from __future__ import annotations

from pathlib import Path

import pytest

from ftc.experiments import tracks

REPO = Path(__file__).resolve().parents[2]
SCENARIOS = REPO / "scenarios"


@pytest.mark.parametrize("path, expected", [
    ("single.toml", "incipient degradation"),
    ("check/deadpump.toml", "dead pump"),  # tank 1's D_T = 8: p(8) = 0 within 10 intervals
    ("check/unseen-noise.toml", "sensor noise"),
    ("check/unseen-continuous.toml", "continuous wear"),
    ("abrupt.toml", "abrupt fault"),  # a factor jump and a stuck valve: the jump names it
])
def test_the_axis_of_the_repository_scenarios(path, expected):
    assert tracks.axis(SCENARIOS / path, intervals=10) == expected


def test_a_stuck_valve_alone_and_a_pump_that_dies_after_the_run(tmp_path):
    single = (SCENARIOS / "single.toml").read_text()
    stuck = tmp_path / "stuck.toml"
    stuck.write_text(single + "\n[[event]]\nat_step = 100\nstuck_valve = 2\nstate = \"open\"\n")
    assert tracks.axis(stuck, intervals=10) == "stuck valve"
    # D_T = 8 kills the pump at age 8: dead within 10 intervals, not within 5
    dead = SCENARIOS / "check" / "deadpump.toml"
    assert tracks.axis(dead, intervals=10) == "dead pump"
    assert tracks.axis(dead, intervals=5) == "incipient degradation"


def test_the_difficulty_is_the_share_closed_gives_up():
    def cell(scenario, seed, k, ref, closed):
        return {"scenario": scenario, "seed": seed, "interval": k,
                "reference_reward_per_step": ref, "closed_reward_per_step": closed}

    # s: intervals 1-2 sum reference 4, closed 3 -> 1 - 3/4 = 0.25; interval 0 ignored
    rows = [cell("s", 0, 0, 9.0, 1.0), cell("s", 0, 1, 2.0, 2.0), cell("s", 0, 2, 2.0, 1.0),
            cell("e", 0, 1, 2.0, 1.96)]
    shares = tracks.closed_share(rows)
    assert shares == pytest.approx({"s": 0.25, "e": 0.02})
    config = tracks.DifficultyConfig(medium_from=0.1, hard_from=0.2)
    assert [tracks.difficulty(v, config) for v in (0.02, 0.1, 0.19, 0.25)] == \
        ["easy", "medium", "medium", "hard"]
    members = tracks.members({"s": {"axis": "dead pump", "difficulty": "hard"},
                              "e": {"axis": "dead pump", "difficulty": "easy"}})
    assert members == {"dead pump": ["s", "e"], "easy": ["e"], "hard": ["s"]}
