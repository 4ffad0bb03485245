"""Fly the students of several adaptive-policy checkpoints as one network
(docs/adaptive.md, "Variants"): the logits of the merged student are the
mean of the checkpoints' students' logits (each checkpoint weighs alike,
whatever its number of members), in one forward pass
(``ftc.learning.history_policy.ensemble``). The checkpoints must be
distinct, trained on the same distribution, and share the window, head,
stuck memory and depth. The merged file holds the merged student as its
policy, the distribution, and under ``merged_from`` each input's path and
training config; no curve, snapshots or training time (it was not trained).

    python scripts/merge_students.py A.pt B.pt [C.pt ...] --out MERGED.pt
    python -m ftc.experiments.adaptive evaluate --checkpoint MERGED.pt ...
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ftc.common.atomic import atomic_torch_save
from ftc.experiments.adaptive.cli import read_checkpoint
from ftc.learning.history_policy import HistoryPolicy, ensemble


def _load(path: Path) -> dict:
    try:
        return read_checkpoint(path)
    except ValueError as e:
        raise SystemExit(f"merge_students: error: {e}") from None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoints", nargs="+", type=Path,
                   help="adaptive-policy checkpoints (train's cache files), two or more")
    p.add_argument("--out", required=True, type=Path, help="the merged checkpoint")
    a = p.parse_args(argv)
    if len(a.checkpoints) < 2:
        p.error("give two or more checkpoints")
    if a.out.resolve() in {c.resolve() for c in a.checkpoints}:
        p.error(f"--out {a.out} is one of the inputs")
    if len({c.resolve() for c in a.checkpoints}) < len(a.checkpoints):
        p.error("a checkpoint is given twice (it would weigh double)")
    records = [_load(c) for c in a.checkpoints]
    distributions = {r.get("distribution") for r in records}
    if len(distributions) > 1:
        raise SystemExit("merge_students: error: the checkpoints were trained on different "
                         "distributions")
    try:
        merged = ensemble([HistoryPolicy.from_record(r["policy"]) for r in records])
    except (KeyError, ValueError, RuntimeError) as e:
        raise SystemExit(f"merge_students: error: the students cannot be merged: "
                         f"{type(e).__name__}: {e}") from None
    out = {"policy": merged.record(), "distribution": records[0].get("distribution"),
           "merged_from": [{"path": str(c), "config": r.get("config")}
                           for c, r in zip(a.checkpoints, records)],
           "snapshots": [], "curve": []}
    atomic_torch_save(a.out, out)
    print(f"merge_students: {len(records)} checkpoints, hidden {merged.config.hidden}, "
          f"written to {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
