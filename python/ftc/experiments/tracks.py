"""Challenge tracks: every scenario labelled by the challenge it poses (its axis)
and by how hard it is (its difficulty), so a method is reported per track.

The axis is read from the scenario as the plant parses it, the first that holds:

* ``sensor noise``: the published levels carry noise (``[noise] std > 0``);
* ``continuous wear``: the components age continuously, not once per interval;
* ``abrupt fault``: an event changes a degradation factor mid-run (whatever
  else happens with it);
* ``stuck valve``: an event sticks a valve;
* ``dead pump``: a tank's pump reaches zero capacity within the run (its factor
  D_T at most the last interval's age: p(a) = p0 max(0, 1 - a / D_T));
* ``incipient degradation``: none of those, the paper's gradual wear.

The difficulty is measured: the share of the reference's reward over intervals
1 on that all valves closed gives up, 1 - sum(closed) / sum(reference) (mean
over seeds). Doing nothing costs little in an easy scenario and much in a hard
one; the cut points (:class:`DifficultyConfig`) are the default suite's terciles
of that share (0.282 and 0.388), measured on the shipped reference scores
(scenarios/reference/suite.json), rounded.
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

AXES = ("incipient degradation", "dead pump", "abrupt fault", "stuck valve", "sensor noise",
        "continuous wear")
DIFFICULTIES = ("easy", "medium", "hard")


@dataclass(frozen=True)
class DifficultyConfig:
    """Cut points of the share of the reference's reward closed gives up.

    medium_from: a scenario at or above this share is medium (below: easy)
    hard_from: at or above this share, hard
    """

    medium_from: float = 0.28
    hard_from: float = 0.39


def axis(path: Path, intervals: int) -> str:
    """The challenge axis of scenario file ``path`` for a run of ``intervals``."""
    from ftc import _core  # native: the plant's own scenario parser

    sc = _core.load_scenario(str(path))
    events = list(sc.events)
    if sc.noise_std > 0:
        return "sensor noise"
    if sc.mode == "continuous":
        return "continuous wear"
    if any("factor" in e for e in events):
        return "abrupt fault"
    if any("stuck_valve" in e for e in events):
        return "stuck valve"
    if any(math.isfinite(f) and f <= intervals - 1 for f in sc.tank_factor):
        return "dead pump"
    return "incipient degradation"


def closed_share(rows: Sequence[Mapping], first_interval: int = 1) -> dict[str, float]:
    """scenario -> 1 - sum(closed) / sum(reference) of rewards per step over intervals
    from ``first_interval`` (results rows with reference_reward_per_step and
    closed_reward_per_step, one method's or several: each cell counted once)."""
    cells = {}
    for r in rows:
        ref, closed = r.get("reference_reward_per_step"), r.get("closed_reward_per_step")
        if int(r["interval"]) >= first_interval and ref is not None and closed is not None:
            cells[(r["scenario"], int(r["seed"]), int(r["interval"]))] = (ref, closed)
    sums: dict = defaultdict(lambda: [0.0, 0.0])
    for (scenario, _, _), (ref, closed) in cells.items():
        sums[scenario][0] += ref
        sums[scenario][1] += closed
    return {s: 1.0 - c / r for s, (r, c) in sums.items() if r > 0}


def difficulty(share: float, config: DifficultyConfig = DifficultyConfig()) -> str:
    """easy, medium or hard for a share of the reference's reward closed gives up."""
    return "hard" if share >= config.hard_from else \
        "medium" if share >= config.medium_from else "easy"


def label(scenario_dir: Path, scenarios: Sequence[str], rows: Sequence[Mapping],
          intervals: int, config: DifficultyConfig = DifficultyConfig()
          ) -> dict[str, dict[str, object]]:
    """scenario -> {"axis", "share", "difficulty"} (share and difficulty None where the
    reference's or closed's rewards are missing)."""
    shares = closed_share(rows)
    out = {}
    for s in scenarios:
        share = shares.get(s)
        out[s] = {"axis": axis(Path(scenario_dir) / f"{s}.toml", intervals), "share": share,
                  "difficulty": None if share is None else difficulty(share, config)}
    return out


def members(labels: Mapping[str, Mapping[str, object]]) -> dict[str, list[str]]:
    """track -> its scenarios: one track per axis and per difficulty, those with a
    scenario, in AXES then DIFFICULTIES order."""
    out = {}
    for name in (*AXES, *DIFFICULTIES):
        chosen = [s for s, lab in labels.items() if name in (lab["axis"], lab["difficulty"])]
        if chosen:
            out[name] = chosen
    return out
