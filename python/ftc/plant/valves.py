"""The valve action every controller hands the plant: six valves, each 0 (closed)
or 1 (open): Gymnasium's ``MultiBinary(6)``. :func:`checked_valves` refuses
anything else (another shape, 2, -1, 0.5, NaN, 257.0) instead of casting it,
since a cast to int8 turns 257.0 into an open valve and 0.99 into a closed one."""

from __future__ import annotations

from typing import Any

import numpy as np

from ftc.common.constants import NUM_TANKS


def valves_problem(action: Any) -> str | None:
    """Why ``action`` is not six valves of 0 or 1 (one line), or None."""
    try:
        u = np.asarray(action)
    except Exception as e:  # noqa: BLE001 - whatever it is, it is not valves
        return f"not an array ({type(e).__name__})"
    if u.dtype == object or not (np.issubdtype(u.dtype, np.number) or u.dtype == bool):
        return f"of type {u.dtype}, not numbers"
    if u.shape != (NUM_TANKS,):
        return f"of shape {u.shape}, not ({NUM_TANKS},)"
    if not np.isin(u, (0, 1)).all():
        return f"{np.array2string(u, separator=', ')} holds values other than 0 and 1"
    return None


def checked_valves(action: Any, who: str) -> np.ndarray:
    """``action`` as int8 valves; ValueError naming ``who`` when it is not six of 0 or 1."""
    problem = valves_problem(action)
    if problem is not None:
        raise ValueError(f"{who}: the action {problem} (six valves, each 0 or 1: "
                         f"MultiBinary({NUM_TANKS}))")
    return np.asarray(action).astype(np.int8)
