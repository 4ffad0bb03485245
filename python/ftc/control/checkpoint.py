"""Checkpoints of interval runs, and the finiteness checks that keep a
non-finite number out of them.

A checkpoint (``checkpoint.pt``, written atomically after every interval) is
everything needed to continue after its last finished interval: the metrics
rows so far, the torch RNG, the configuration it was written under and the
agent's own state. It is read with ``torch.load(weights_only=True)`` (tensors,
arrays and plain containers: no unpickling of code) and checked against the
run's configuration before any of it is used.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ftc.common.atomic import atomic_torch_save
from ftc.common.errors import CheckpointError, NonFiniteError
from ftc.control import registry
from ftc.control.config import EXTENSIBLE_FIELDS, run_local_fields
from ftc.learning.transitions import Transitions
from ftc.plant.link import PlantObservation

FORMAT = 3
KEYS = frozenset({"format", "interval", "rows", "info", "torch_rng", "config", "agent"})


def config_stamp(configs: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """What a checkpoint must agree with to be resumed: every config part,
    without the fields that do not change results and those a resumed run may
    raise (its intervals), as plain JSON values."""
    stamp = {}
    for part, cfg in configs.items():
        local = run_local_fields(cfg)
        values = {k: v for k, v in dataclasses.asdict(cfg).items()
                  if k not in local and k not in EXTENSIBLE_FIELDS}
        stamp[part] = json.loads(json.dumps(values, default=str))
    return stamp


def save(path: Path, state: dict[str, Any]) -> None:
    atomic_torch_save(path, {"format": FORMAT, **state})


def read(path: Path) -> dict[str, Any]:
    """The checkpoint at ``path``, checked only for being readable, of this
    format and complete (the exporter's view; :func:`load` checks the rest);
    raises CheckpointError saying why not."""
    if not path.is_file():
        raise CheckpointError(f"{path}: no checkpoint (the run stopped before its first "
                              "interval finished: nothing to resume; start it again with "
                              "--overwrite in place of --resume)")
    try:
        state = torch.load(path, weights_only=True)
    except Exception as e:  # noqa: BLE001 - any failure to read means corrupt
        reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise CheckpointError(f"{path}: corrupt or truncated checkpoint "
                              f"({type(e).__name__}: {reason[:200]})") from None
    if not isinstance(state, dict) or "format" not in state:
        raise CheckpointError(f"{path}: not a run checkpoint of this version (no format record)")
    if state["format"] != FORMAT:
        raise CheckpointError(f"{path}: checkpoint format {state['format']!r}, this "
                              f"version reads format {FORMAT}")
    missing = sorted(KEYS - set(state))
    if missing:
        raise CheckpointError(f"{path}: checkpoint lacks {', '.join(missing)}")
    return state


def load(path: Path, configs: dict[str, Any], intervals: int) -> dict[str, Any]:
    """``path`` checked: readable, of this format, written under the same
    configuration, consistent; raises CheckpointError saying why not."""
    state = read(path)
    mine = config_stamp(configs)
    theirs = state["config"] if isinstance(state["config"], dict) else {}
    for part in theirs.values():  # a run written under a former name of its method
        if isinstance(part, dict) and isinstance(part.get("method"), str):
            part["method"] = registry.canonical(part["method"])
    diffs = [f"{part}.{key} {theirs.get(part, {}).get(key)!r} in the checkpoint, {value!r} here"
             for part in mine for key, value in mine[part].items()
             if theirs.get(part, {}).get(key) != value]
    if diffs:
        raise CheckpointError(f"{path}: written by a run with another configuration: "
                              + "; ".join(diffs[:4]) + (" ..." if len(diffs) > 4 else ""))
    interval = state["interval"]
    if not (isinstance(interval, int) and 0 < interval <= intervals
            and len(state["rows"]) == interval):
        raise CheckpointError(f"{path}: inconsistent checkpoint (interval {interval!r}, "
                              f"{len(state['rows'])} metrics rows, {intervals} intervals "
                              "configured)")
    return state


def check_network_shapes_of(ours: dict[str, torch.Tensor], theirs: Any, what: str) -> None:
    """A saved state dict has the same tensors, of the same shapes, as ``ours``."""
    theirs = theirs if isinstance(theirs, dict) else {}
    if set(ours) != set(theirs):
        raise CheckpointError(f"{what} layers differ from this run's "
                              f"(checkpoint {len(theirs)} tensors, here {len(ours)})")
    for name, tensor in ours.items():
        if tuple(theirs[name].shape) != tuple(tensor.shape):
            raise CheckpointError(
                f"{what} sizes differ: {name} is {tuple(theirs[name].shape)} "
                f"in the checkpoint, {tuple(tensor.shape)} in this run's configuration")


def transitions_state(t: Transitions) -> dict[str, torch.Tensor]:
    return {k: torch.as_tensor(getattr(t, k)) for k in ("level", "valves", "next_level", "episode")}


def transitions_from_state(d: dict[str, torch.Tensor]) -> Transitions:
    return Transitions(**{k: v.numpy() for k, v in d.items()})


# --------------------------------------------------------------------------
# Finiteness
# --------------------------------------------------------------------------

def finite_observation(o: PlantObservation, where: str) -> PlantObservation:
    if not np.all(np.isfinite(o.level)):
        raise NonFiniteError(f"non-finite observation at {where}: levels {o.level.tolist()}")
    return o


def check_finite_state(state: dict[str, Any], what: str) -> None:
    """Every floating tensor in a (nested) state dict is finite."""
    for name, value in state.items():
        if isinstance(value, dict):
            check_finite_state(value, what)
        elif torch.is_tensor(value) and value.is_floating_point() \
                and not bool(torch.isfinite(value).all()):
            raise NonFiniteError(f"non-finite {what} ({name})")


def check_update(policy: torch.nn.Module, stats: Any, what: str) -> None:
    """After an update: losses, then the last gradients, then the weights finite
    (a non-finite gradient of an earlier minibatch shows in the weights)."""
    for name in ("policy_loss", "value_loss", "entropy", "approx_kl"):
        if not math.isfinite(getattr(stats, name)):
            raise NonFiniteError(f"non-finite loss in {what}: {name} = {getattr(stats, name)}")
    for name, param in policy.named_parameters():
        if param.grad is not None and not bool(torch.isfinite(param.grad).all()):
            raise NonFiniteError(f"non-finite gradient in {what} ({name})")
    for name, param in policy.named_parameters():
        if not bool(torch.isfinite(param).all()):
            raise NonFiniteError(f"non-finite weights after {what} ({name}): a non-finite "
                                 "gradient reached them")
