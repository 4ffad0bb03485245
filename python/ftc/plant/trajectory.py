"""The trajectory schema: the one definition of the per-step CSV columns that
simulate, the experiments' baseline episodes and replay write (and figures
and tests read by name).

    episode, step, age[, evaluation, terminal, truncated], u1..u6, x1..x6[, reward]

``step`` counts from 1 in each episode (0: the initial state), ``age`` is the
degradation age in force during the step (intervals), ``u`` the valves applied
during the step, ``x`` the levels after it (m), ``reward`` the step's reward.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

from ftc.common.constants import NUM_TANKS

VALVE_COLUMNS = [f"u{i}" for i in range(1, NUM_TANKS + 1)]
LEVEL_COLUMNS = [f"x{i}" for i in range(1, NUM_TANKS + 1)]
FLAG_COLUMNS = ["evaluation", "terminal", "truncated"]


def header(flags: bool = False, reward: bool = False) -> list[str]:
    """The columns, with the episode flags and the reward or without."""
    return ["episode", "step", "age", *(FLAG_COLUMNS if flags else []), *VALVE_COLUMNS,
            *LEVEL_COLUMNS, *(["reward"] if reward else [])]


def exact(x: float) -> str:
    """A level or reward written so that it reads back to the same float."""
    return repr(float(x))


def row(episode: int, step: int, age: float, valves: Sequence[int], levels: Sequence[float], *,
        flags: Sequence[int] | None = None, reward: float | str | None = None,
        level_format: Callable[[float], str] = exact) -> list[Any]:
    """One CSV row in the order of :func:`header` (flags and reward when given)."""
    cells: list[Any] = [int(episode), int(step), f"{age:.6g}"]
    if flags is not None:
        cells += [int(f) for f in flags]
    cells += [int(u) for u in valves]
    cells += [level_format(x) for x in levels]
    if reward is not None:
        cells.append(reward if isinstance(reward, str) else exact(reward))
    return cells
