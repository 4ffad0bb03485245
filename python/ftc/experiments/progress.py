"""The experiments' progress line: runs done/total, each running run's current
interval, elapsed time and ETA (on a terminal one line redrawn in place,
otherwise a line every 10 s)."""

from __future__ import annotations

import math
import shutil
import sys
import time
from pathlib import Path
from typing import Iterable, TextIO

from ftc.experiments.methods import METHODS
from ftc.experiments.processes import RunHandle
from ftc.experiments.runs import RunSpec


def format_duration(s: float) -> str:
    """``1h02m`` or ``3m04s``; ``?`` for an unknown (infinite) duration."""
    if not math.isfinite(s):
        return "?"
    s = int(round(s))
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


def count_rows(path: Path) -> int:
    """Data rows in a CSV being written by another process (0 if absent)."""
    try:
        with open(path) as f:
            return max(0, sum(1 for line in f if line.strip()) - 1)
    except OSError:
        return 0


class Progress:
    """Runs done/total, each running run's current interval, elapsed time and ETA.

    The ETA weighs each run's intervals by its method's cost and extrapolates
    the rate of this orchestrator's progress.
    """

    def __init__(self, runs: list[RunSpec], finished: set[str], intervals: int,
                 stream: TextIO = sys.stderr) -> None:
        self.runs, self.intervals, self.stream = runs, intervals, stream
        self.done = set(finished)
        self.runs_keys = {r.key for r in runs}
        self.failed: set[str] = set()
        self.start = time.time()
        self.done_at_start = self._work(self.done)
        self.total = self._work(r.key for r in runs)
        self.tty = stream.isatty()
        self._last_line = 0.0

    def _cost(self, key: str) -> float:
        return METHODS[key.split("/")[2]].cost

    def _work(self, keys: Iterable[str]) -> float:
        return sum(self._cost(k) * self.intervals for k in keys)

    def due(self, final: bool = False) -> bool:
        """Whether a line is to be drawn now (always on a terminal, else every 10 s)."""
        return self.tty or final or time.time() - self._last_line >= 10.0

    def show(self, running: dict[str, RunHandle], final: bool = False) -> None:
        """The line for runs whose processes run here (their metrics.csv is read)."""
        if not self.due(final):
            return
        self.show_counts({k: count_rows(h.directory / "controller" / "metrics.csv")
                          for k, h in running.items()}, final)

    def show_counts(self, partial: dict[str, int], final: bool = False) -> None:
        """The line, given each running run's finished intervals (``partial``:
        key -> intervals done; the Ray executor's tasks report them)."""
        now = time.time()
        if not self.due(final):
            return
        self._last_line = now
        work = self._work(self.done) + sum(self._cost(k) * n for k, n in partial.items())
        rate = (work - self.done_at_start) / max(now - self.start, 1e-9)
        eta = (self.total - work) / rate if rate > 0 else math.inf
        parts = [f"{k} int {min(n + 1, self.intervals)}/{self.intervals}"
                 for k, n in sorted(partial.items())]
        line = (f"[{len(self.done)}/{len(self.runs)} runs done"
                + (f", {len(self.failed)} failed" if self.failed else "")
                + f"] elapsed {format_duration(now - self.start)}, ETA {format_duration(eta)}"
                + (f" | {'; '.join(parts)}" if parts else ""))
        if self.tty:
            width = shutil.get_terminal_size((120, 20)).columns
            self.stream.write("\r" + line[:width - 1].ljust(width - 1) + ("\n" if final else ""))
        else:
            self.stream.write(line + "\n")
        self.stream.flush()
