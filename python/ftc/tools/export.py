"""Export the trained policy of a controller checkpoint to ONNX, for a
controller on the embedded side (docs/ecosystem.md has the C++ side).

    python -m ftc.export runs/s0/checkpoint.pt --out policy.onnx
    python -m ftc.export runs/s0 --out policy.onnx        # a run directory: its checkpoint.pt

The graph is the deterministic action path of the PPO policy, the one the
runner's evaluation episodes use (learning.ppo.ActorCritic.act, deterministic):

    input   levels  float32 [N, 6]  tank levels after the last step, metres, tanks 1..6
                                    (PlantObservation.level; the graph maps them to
                                    [-1, 1] itself: no normalisation outside)
    output  valves  int8    [N, 6]  valve commands, 1 open / 0 closed, tanks 1..6: the
                                    valve_command_t.valve values as they are
    output  logits  float32 [N, 6]  per-valve Bernoulli logits; valve i opens iff
                                    logits[i] > 0; p(open) = 1 / (1 + exp(-logit))

N is dynamic (1 for a controller acting step by step). Only PPO runs
(ftc.controller --method ppo or ppo-robust) have a policy network; the
critic is left out.

The adaptive student's checkpoint (``python -m ftc.experiments.adaptive
train``; docs/adaptive.md) exports as --weights only: an ``ftc-policy 2``
file with its history window, version 1, which build/policy_node flies with
either head (the node tells them by the output width: 6 valve logits, or the
joint head's 64, one per valve setting). After the export the tool runs the ONNX model in
onnxruntime on fixed-seed states over the observation space and refuses to
write a model whose valves differ from torch's; the .onnx is written
atomically.

An existing --out is refused unless --overwrite; while the tool runs,
.NAME.lock beside --out keeps a second writer out.

Errors: one line on stderr ("ftc.export: error: ..."); exit 2 for bad input (a
missing, corrupt or truncated checkpoint, one of a run without a policy, a bad
--out, an --out that exists or is being written by another export), 5 when the
file cannot be written, 1 when the export itself fails.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys
import warnings
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np
import torch
from torch import nn

from ftc.common.atomic import atomic_write_bytes
from ftc.common.build_info import git_revision
from ftc.common.cli import OneLineParser, at_least, check_out_file, checked
from ftc.common.errors import CheckpointError, NonFiniteError, RunError
from ftc.common.run_lock import RunLock, refuse_existing
from ftc.control.run import checkpoint
from ftc.tools.run_cli import run_or_report
from ftc.learning.buffer import NUM_VALVES, OBS_DIM
from ftc.learning.history_policy import HistoryPolicy
from ftc.learning.ppo import ActorCritic
from ftc.control.run import policy_weights

TOOL = "ftc.export"
INPUT = "levels"
OUTPUTS = ("valves", "logits")
EXPORTABLE = ("ppo", "ppo-robust")  # controller methods whose agent state holds a policy
# onnxruntime vs torch on the logits, float32: |difference| <= ATOL + RTOL x the
# state's largest |logit| (float32 rounds relative to the terms summed, and the
# largest logit bounds them; measured: < 1e-6 on a fresh policy, 2.1e-5 on a
# distilled ppo-robust policy whose logits reach the hundreds)
LOGIT_ATOL = 1e-5
LOGIT_RTOL = 1e-5


class DeterministicPolicy(nn.Module):
    """levels (N, 6) m -> (valves (N, 6) int8, logits (N, 6)): the greedy action."""

    def __init__(self, policy: ActorCritic) -> None:
        super().__init__()
        self.policy = policy

    def forward(self, levels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        logits, _ = self.policy(levels)  # the value head is pruned from the graph
        return (logits > 0).to(torch.int8), logits


def checkpoint_path(given: Path) -> Path:
    """The checkpoint file: ``given``, or a run directory's checkpoint.pt."""
    return given / "checkpoint.pt" if given.is_dir() else given


def load_student(path: Path) -> HistoryPolicy | None:
    """The adaptive student of a checkpoint ``python -m ftc.experiments.adaptive
    train`` wrote (a record whose ``policy`` holds a ``config`` and a ``state``,
    and no run ``format``), or None when ``path`` holds anything else;
    CheckpointError if its student does not load."""
    if not path.is_file():
        return None
    try:
        record = torch.load(path, weights_only=True)
    except Exception:  # noqa: BLE001 - not ours to judge: load_policy says why
        return None
    student = record.get("policy") if isinstance(record, dict) else None
    if not isinstance(student, dict) or "format" in record or \
            not {"config", "state"} <= set(student):  # HistoryPolicy.record()'s
        return None
    try:
        student = HistoryPolicy.from_record(record["policy"])
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        reason = str(e).strip().splitlines()[0][:200] if str(e).strip() else ""
        raise CheckpointError(f"{path}: an adaptive-policy checkpoint whose student does not "
                              f"load ({type(e).__name__}: {reason})") from None
    if not all(torch.isfinite(p).all() for p in student.parameters()):
        raise CheckpointError(f"{path}: the student's weights are not all finite")
    return student


def load_policy(path: Path) -> tuple[ActorCritic, dict[str, Any]]:
    """The policy network of the PPO run checkpoint at ``path`` and what it came
    from (method, seed, interval); raises CheckpointError saying why not."""
    if not path.exists():
        raise CheckpointError(f"{path}: no such checkpoint")
    state = checkpoint.read(path)
    config = state["config"] if isinstance(state["config"], dict) else {}
    if "controller" not in config:
        kind = ", ".join(f"{part} --method {values.get('method')}" for part, values
                         in config.items() if isinstance(values, dict)) or "unknown"
        raise CheckpointError(f"{path}: a checkpoint of a run without a policy network "
                              f"({kind}); only ftc.controller --method "
                              f"{' or '.join(EXPORTABLE)} runs can be exported")
    method = config["controller"].get("method")
    if method not in EXPORTABLE:
        raise CheckpointError(f"{path}: a checkpoint of a --method {method} run, which has no "
                              f"policy network; only --method {' or '.join(EXPORTABLE)} "
                              "runs can be exported")
    agent = state["agent"] if isinstance(state["agent"], dict) else {}
    weights = agent.get("ppo", {}).get("policy") if isinstance(agent.get("ppo"), dict) else None
    if not isinstance(weights, dict):
        raise CheckpointError(f"{path}: the checkpoint's agent state has no policy weights")
    ppo = config.get("ppo", {})
    try:
        policy = ActorCritic(tuple(ppo["trunk_sizes"]), tuple(ppo["head_sizes"]))
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"{path}: the checkpoint's network sizes are unreadable "
                              f"({type(e).__name__}: {e})") from None
    checkpoint.check_network_shapes_of(policy.state_dict(), weights, f"{path}: network")
    try:
        checkpoint.check_finite_state(weights, "policy weights in the checkpoint")
        policy.load_state_dict(weights)
    except NonFiniteError as e:
        raise CheckpointError(f"{path}: {e}") from None
    except (RuntimeError, ValueError) as e:
        raise CheckpointError(f"{path}: the policy does not load: "
                              f"{str(e).strip().splitlines()[0][:200]}") from None
    source = {"method": method, "seed": config["controller"].get("seed"),
              "interval": state["interval"], "checkpoint": str(path.resolve())}
    return policy.eval(), source


@contextlib.contextmanager
def _quiet_exporter() -> Iterator[None]:
    """Silence two notices torch 2.13's exporter prints about itself, not about
    the model: the torchvision operators it skips (not installed) and a pytree
    deprecation raised inside torch.export's decomposition."""
    registration = logging.getLogger("torch.onnx._internal.exporter._registration")
    level = registration.level
    registration.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=r".*LeafSpec.*", category=FutureWarning)
            yield
    finally:
        registration.setLevel(level)


def export_model(policy: ActorCritic, source: dict[str, Any]) -> Any:
    """The checked ``onnx.ModelProto`` of ``policy``'s deterministic action path
    (torch.onnx's dynamo exporter, a dynamic batch dimension)."""
    try:  # optional and heavy (requirements-extra.txt): imported only here
        import onnx
    except ImportError:
        raise RunError("onnx is not installed (pip install -r requirements-extra.txt)") from None
    example = torch.rand(8, OBS_DIM, generator=torch.Generator().manual_seed(0))
    try:
        with _quiet_exporter():
            program = torch.onnx.export(
                DeterministicPolicy(policy).eval(), (example,), dynamo=True, verbose=False,
                input_names=[INPUT], output_names=list(OUTPUTS),
                dynamic_shapes={INPUT: {0: torch.export.Dim("batch")}})
        model = program.model_proto
        onnx.checker.check_model(model, full_check=True)
    except Exception as e:  # noqa: BLE001 - any exporter failure ends the tool
        reason = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise RunError(f"ONNX export failed ({type(e).__name__}: {reason[:200]})") from None
    model.doc_string = (f"ftc PPO policy, deterministic action path: {INPUT} float32 [N, 6] tank "
                        "levels (m) -> valves int8 [N, 6] (1 open), logits float32 [N, 6] "
                        "(open iff > 0). docs/ecosystem.md")
    onnx.helper.set_model_props(model, {
        **{f"ftc.{k}": str(v) for k, v in source.items()},
        "ftc.git_revision": git_revision() or "unknown"})
    return model


def sample_levels(n: int, seed: int = 0) -> np.ndarray:
    """``n`` observations over the observation space (n, 6) float32: uniform in
    [0, 1] m (empty to full tanks), after the 64 corners of the cube."""
    corners = ((np.arange(2 ** OBS_DIM)[:, None] >> np.arange(OBS_DIM)) & 1).astype(np.float32)
    rng = np.random.default_rng(seed)
    uniform = rng.uniform(0.0, 1.0, (max(n - len(corners), 0), OBS_DIM)).astype(np.float32)
    return np.concatenate([corners, uniform])[:n]


def verify(model: Any, policy: ActorCritic, states: int) -> float:
    """onnxruntime's valves on ``states`` sampled states equal torch's deterministic
    actions, and its logits agree within LOGIT_ATOL + LOGIT_RTOL x the state's
    largest |logit|;
    returns the largest logit difference. Raises RunError otherwise."""
    try:
        import onnxruntime
    except ImportError:
        raise RunError("onnxruntime is not installed (pip install -r requirements-extra.txt; "
                       "or --verify-states 0)") from None
    x = sample_levels(states)
    session = onnxruntime.InferenceSession(model.SerializeToString(),
                                           providers=["CPUExecutionProvider"])
    valves, logits = session.run(list(OUTPUTS), {INPUT: x})
    with torch.no_grad():
        actions, _, _ = policy.act(torch.from_numpy(x), deterministic=True)
        expected_logits, _ = policy(torch.from_numpy(x))
    differ = int((valves != actions.numpy().astype(np.int8)).any(axis=1).sum())
    expected = expected_logits.numpy()
    difference = np.abs(logits - expected)
    gap = float(difference.max())
    scale = np.abs(expected).max(axis=1, keepdims=True)
    beyond = int((difference > LOGIT_ATOL + LOGIT_RTOL * scale).any(axis=1).sum())
    if differ or beyond or valves.shape != (states, NUM_VALVES):
        raise RunError(f"the exported model disagrees with torch on {states} states: valves "
                       f"on {differ}, logits beyond {LOGIT_ATOL:g} + {LOGIT_RTOL:g} x max |logit| "
                       f"on {beyond} (largest difference {gap:.3g}); nothing written")
    return gap


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="python -m ftc.export", allow_abbrev=False,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1])
    parser.add_argument("checkpoint", type=checked(Path, nonempty=True),
                        help="a controller checkpoint.pt (or its run directory)")
    parser.add_argument("--out", type=checked(Path, nonempty=True),
                        help="the .onnx file to write (atomically)")
    parser.add_argument("--weights", type=checked(Path, nonempty=True),
                        help="also (or only) write the weights file build/policy_node reads "
                             "(ftc.control.run.policy_weights has its format), atomically")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace an existing --out file (atomically, once the new model "
                             "is verified; default: refuse it)")
    parser.add_argument("--verify-states", type=checked(int, at_least(0, 10_000_000)),
                        default=4096, help="states on which onnxruntime must agree with torch "
                        "before the file is written (0: no check; default: %(default)s)")
    return parser


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """The command line; a bad --out exits 2 with one line before anything runs."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.out is None and args.weights is None:
        parser.error("give --out (the .onnx file), --weights (the node's weights file) or both")
    if args.out is not None:
        check_out_file(parser, args.out, args.overwrite, "the .onnx file")
    if args.weights is not None:
        check_out_file(parser, args.weights, args.overwrite, "the weights file")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    torch.set_num_threads(1)

    def run() -> None:
        first = args.out if args.out is not None else args.weights
        with RunLock(first, TOOL, beside=True) as lock:
            lock.announce_takeover()
            for target in (args.out, args.weights):  # again, now that no one else writes
                if target is not None:
                    refuse_existing(target, args.overwrite)
            path = checkpoint_path(args.checkpoint)
            student = load_student(path)
            if student is not None:
                if args.out is not None:
                    raise CheckpointError(
                        f"{path}: an adaptive-policy student (a history window of "
                        f"{student.config.window} steps) exports as --weights only: the ONNX "
                        "graph takes the levels alone")
                window, widths, params = policy_weights.student_layers(student)
                memory = student.config.stuck_memory
                policy_weights.write_weights(args.weights, widths, params, version=1,
                                             window=window, stuck_memory=memory)
                print(f"{TOOL}: wrote {args.weights} (adaptive-policy student of {path}, "
                      f"window {window}{', stuck memory' if memory else ''}, widths "
                      f"{' '.join(map(str, widths))}, version 1)")
                return
            policy, source = load_policy(path)
            written = []
            if args.out is not None:
                model = export_model(policy, source)
                gap = verify(model, policy, args.verify_states) if args.verify_states else None
                atomic_write_bytes(args.out, model.SerializeToString())
                written.append(str(args.out) + (
                    f" (onnxruntime agrees on {args.verify_states} states, logits within "
                    f"{gap:.2g})" if gap is not None else ""))
            if args.weights is not None:
                widths, params = policy_weights.actor_layers(policy)
                policy_weights.write_weights(args.weights, widths, params,
                                             version=int(source["interval"]) + 1)
                written.append(str(args.weights))
        print(f"{TOOL}: wrote {' and '.join(written)} ({source['method']} policy of {path}, "
              f"after {source['interval']} intervals)")

    return run_or_report(TOOL, run)


if __name__ == "__main__":
    sys.exit(main())
