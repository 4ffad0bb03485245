"""The policy's weights for the embedded controller (``build/policy_node``):
the weights file ``ftc.export --weights`` writes, and the ``policy_t`` /
``policy_v2_t`` message that pushes new weights to a running node.

    python -m ftc.export runs/s0 --weights policy.txt
    ./build/policy_node --policy policy.txt --lcm-url 'udpm://239.255.76.67:7667?ttl=0' --prefix RT_
    python -m ftc.tools.policy_weights push policy.txt --version 2 --lcm-url ... --prefix RT_
    python -m ftc.controller ... --push-policy RT_ --push-url ...   (after every interval)

The weights file (text, ``ftc-policy 1``)::

    ftc-policy 1
    version 1
    widths 6 64 64 16 16 6
    params 5734
    <the params, whitespace-separated, 9 significant digits (float32 exactly)>
    checksum 0123456789abcdef

The actor as a chain of dense layers: the input is the levels in metres
mapped to 2 x - 1; every layer but the last is followed by tanh; a valve
opens where its logit (the last layer's output) is positive, as the policy's
deterministic action. ``params`` holds, layer by layer, W (inputs x outputs,
row-major) then b. ``checksum``: FNV-1a 64 of the widths (int32
little-endian) then the params (float32 little-endian), in hex; the node
refuses a file or push whose checksum differs, a version not above its own,
or widths that are not 6 -> ... -> 6 (12 W -> ... -> 6 or 64 with a window,
below), naming the reason, and keeps its policy.
It answers every push on ``<prefix>POLICY_ACK`` (accepted, or rejected with
the reason): :func:`push` waits for that answer.

A policy with a history window (the adaptive student,
:mod:`ftc.learning.history_policy`) is written as ``ftc-policy 2``: a
``window W`` line after the version, widths from ``12 W`` (the last W steps,
newest first, each the six levels and the six valves commanded before them,
``2 x - 1``), and the checksum continued over the window (int32
little-endian) after the params. A student that also reads its stuck memory
(the valves it has seen applied otherwise than commanded, 12 inputs after
the window: :class:`ftc.learning.history_policy.HistoryWindow`) has a
``stuck_memory 1`` line after the window, widths from ``12 W + 12``, and its
checksum continued with the int32 1. Its last layer is 6 logits (a valve opens
where its logit is positive) or 64, one per valve setting: the node applies
the setting of the largest (the first on ties), valve i open where bit i is set. It is pushed as a ``policy_v2_t`` (a window
field); policies of the levels stay ``ftc-policy 1`` files and ``policy_t``
pushes, so a node that predates the window takes them as before and refuses a
``policy_v2_t`` as not a ``policy_t`` in its answer.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ftc.common.atomic import atomic_write_text
from ftc.common.constants import NUM_TANKS
from ftc.common.errors import UsageError
from ftc.plant.lcm_link import check_loopback_url
from ftc.plant.signing import Auth
from ftc.plant.wire import decode_ack

FORMAT = "ftc-policy 1"
FORMAT_WINDOW = "ftc-policy 2"  # with a history window
STEP_FEATURES = 2 * NUM_TANKS  # a window step's levels and valves, and the stuck memory's width
FNV_OFFSET, FNV_PRIME, MASK = 1469598103934665603, 1099511628211, (1 << 64) - 1


def window_inputs(window: int, stuck_memory: bool) -> int:
    """The input width of a policy that reads the last ``window`` steps (12
    floats each) and, with ``stuck_memory``, the memory's 12 after them
    (``StudentConfig.inputs``). ValueError for the memory without a window."""
    if stuck_memory and not window:
        raise ValueError("the stuck memory is read after a history window (window 0 given)")
    return STEP_FEATURES * int(window) + (STEP_FEATURES if stuck_memory else 0)


def checksum(widths: Sequence[int], params: np.ndarray, window: int | None = None,
             stuck_memory: bool = False) -> int:
    """FNV-1a 64 of the widths (int32 LE) then the params (float32 LE), then
    the window (int32 LE) when given (``ftc-policy 2``, ``policy_v2_t``), then
    the int32 1 for a policy that reads the stuck memory."""
    data = (np.asarray(widths, "<i4").tobytes() + np.asarray(params, "<f4").tobytes()
            + (b"" if window is None else np.asarray([window], "<i4").tobytes())
            + (np.asarray([1], "<i4").tobytes() if stuck_memory else b""))
    h = FNV_OFFSET
    for byte in data:
        h = ((h ^ byte) * FNV_PRIME) & MASK
    return h


@dataclass(frozen=True)
class Weights:
    """A weights file's contents: ``window`` 0 for a policy of the levels;
    ``stuck_memory``: its input ends with the stuck memory."""

    widths: list[int]
    params: np.ndarray
    version: int
    window: int = 0
    stuck_memory: bool = False


def actor_layers(policy) -> tuple[list[int], np.ndarray]:
    """(widths, params float32) of an :class:`ftc.learning.ppo.ActorCritic`'s
    actor: its trunk's layers then its policy head's, each W (in x out) then b."""
    import torch

    linears = [m for part in (policy.trunk, policy.policy_head) for m in part.modules()
               if isinstance(m, torch.nn.Linear)]
    widths = [linears[0].in_features, *(m.out_features for m in linears)]
    params = np.concatenate([np.concatenate([m.weight.detach().numpy().T.ravel(),
                                             m.bias.detach().numpy()]) for m in linears])
    return widths, params.astype(np.float32)


def student_layers(policy) -> tuple[int, list[int], np.ndarray]:
    """(window, widths, params float32) of a
    :class:`ftc.learning.history_policy.HistoryPolicy`: its dense layers in
    order, each W (in x out) then b (its ``config.stuck_memory`` says whether
    its input ends with the stuck memory)."""
    import torch

    linears = [m for m in policy.net.modules() if isinstance(m, torch.nn.Linear)]
    widths = [linears[0].in_features, *(m.out_features for m in linears)]
    params = np.concatenate([np.concatenate([m.weight.detach().numpy().T.ravel(),
                                             m.bias.detach().numpy()]) for m in linears])
    return int(policy.config.window), widths, params.astype(np.float32)


def actions(widths: Sequence[int], params: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """The valves (N, 6) int8 the node computes for levels (N, 6): the format's
    arithmetic in NumPy (float32), for checks."""
    x = 2.0 * np.asarray(levels, np.float32) - 1.0
    offset = 0
    for i, (n_in, n_out) in enumerate(zip(widths[:-1], widths[1:])):
        w = params[offset:offset + n_in * n_out].reshape(n_in, n_out)
        b = params[offset + n_in * n_out:offset + (n_in + 1) * n_out]
        offset += (n_in + 1) * n_out
        x = x @ w + b
        if i < len(widths) - 2:
            x = np.tanh(x)
    return (x > 0).astype(np.int8)


def format_weights(widths: Sequence[int], params: np.ndarray, version: int = 1,
                   window: int = 0, stuck_memory: bool = False) -> str:
    """The weights file's text: ``ftc-policy 1``, or ``2`` with ``window`` >= 1
    (and a ``stuck_memory 1`` line after the window for a policy that reads it)."""
    window_inputs(window, stuck_memory)  # refuses the memory without a window
    params = np.asarray(params, np.float32)
    rows = [" ".join(f"{v:.9g}" for v in params[i:i + 8]) for i in range(0, len(params), 8)]
    head = [FORMAT_WINDOW, f"version {int(version)}", f"window {int(window)}"] if window else \
        [FORMAT, f"version {int(version)}"]
    if stuck_memory:
        head.append("stuck_memory 1")
    return "\n".join([*head, "widths " + " ".join(map(str, widths)),
                      f"params {len(params)}", *rows,
                      f"checksum {checksum(widths, params, window or None, stuck_memory):016x}"]
                     ) + "\n"


def write_weights(path: Path, widths: Sequence[int], params: np.ndarray, version: int = 1,
                  window: int = 0, stuck_memory: bool = False) -> None:
    atomic_write_text(Path(path), format_weights(widths, params, version, window, stuck_memory))


def read_weights(path: Path) -> tuple[list[int], np.ndarray, int]:
    """(widths, params, version) of an ``ftc-policy 1`` weights file (a policy
    of the levels); UsageError naming the file and what is wrong, a file with
    a window included (:func:`read_policy` reads both)."""
    weights = read_policy(path)
    if weights.window:
        raise UsageError(f"{path}: a policy with a history window of {weights.window} steps "
                         f"({FORMAT_WINDOW}), not a policy of the levels")
    return weights.widths, weights.params, weights.version


def read_policy(path: Path) -> Weights:
    """A weights file of either format; UsageError naming the file and what is
    wrong (the node's checks)."""
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except OSError as e:
        raise UsageError(f"{path}: cannot read the weights file ({e.strerror})") from None
    if not lines or lines[0].strip() not in (FORMAT, FORMAT_WINDOW):
        raise UsageError(f"{path}:1: not an {FORMAT} or {FORMAT_WINDOW} weights file")
    windowed = lines[0].strip() == FORMAT_WINDOW
    fields, values = {}, []
    for n, line in enumerate(lines[1:], start=2):
        head, _, rest = line.partition(" ")
        if head in ("version", "widths", "params", "checksum") or (
                windowed and head in ("window", "stuck_memory")):
            fields[head] = rest.split()
        elif line.strip() and not line.startswith("#"):
            try:
                values += [float(v) for v in line.split()]
            except ValueError:
                raise UsageError(f"{path}:{n}: a number expected: {line[:40]!r}") from None
    try:
        widths = [int(w) for w in fields["widths"]]
        count, version = int(fields["params"][0]), int(fields.get("version", ["0"])[0])
        expected = int(fields["checksum"][0], 16)
        window = int(fields["window"][0]) if windowed else None
        memory = int(fields.get("stuck_memory", ["0"])[0])
        if memory not in (0, 1):
            raise ValueError(memory)
    except (KeyError, IndexError, ValueError):
        raise UsageError(f"{path}: a version, {'window, ' if windowed else ''}widths, params or "
                         "checksum line is missing or malformed") from None
    params = np.asarray(values, np.float32)
    if len(params) != count:
        raise UsageError(f"{path}: params says {count} values, the file holds {len(params)} "
                         "(truncated?)")
    if checksum(widths, params, window, bool(memory)) != expected:
        raise UsageError(f"{path}: checksum mismatch: the weights were changed or truncated")
    if window is not None:
        from ftc.policy_v2_t import policy_v2_t  # generated by lcm-gen at build time

        if not 1 <= window <= policy_v2_t.MAX_WINDOW:
            raise UsageError(f"{path}: a window of {window} steps (allowed: "
                             f"1..{policy_v2_t.MAX_WINDOW})")
        inputs = window_inputs(window, bool(memory))
        if widths[:1] != [inputs]:
            raise UsageError(f"{path}: widths must start at {inputs} (a window of {window} "
                             f"steps{', then the stuck memory' if memory else ''}), got "
                             f"{widths[:1] or 'none'}")
    return Weights(widths, params, version, window or 0, bool(memory))


def policy_message(widths: Sequence[int], params: np.ndarray, version: int,
                   checksum_value: int | None = None, window: int = 0,
                   stuck_memory: bool = False):
    """A ``policy_t`` carrying the weights (its checksum computed unless given),
    or with ``window`` >= 1 a ``policy_v2_t`` carrying the window (and whether
    the policy reads the stuck memory) too."""
    window_inputs(window, stuck_memory)  # refuses the memory without a window
    if window:
        from ftc.policy_v2_t import policy_v2_t  # generated by lcm-gen at build time

        msg = policy_v2_t()
        msg.window = int(window)
        msg.stuck_memory = int(bool(stuck_memory))
    else:
        from ftc.policy_t import policy_t  # generated by lcm-gen at build time

        msg = policy_t()
    msg.utime, msg.version = int(time.time() * 1e6), int(version)
    msg.num_widths, msg.widths = len(widths), [int(w) for w in widths]
    msg.num_params, msg.params = len(params), [float(v) for v in np.asarray(params, np.float32)]
    value = (checksum(widths, params, window or None, stuck_memory) if checksum_value is None
             else checksum_value)
    msg.checksum = value - (1 << 64) if value >= 1 << 63 else value  # int64 on the wire
    return msg


# metrics.csv's columns of a run that pushes its policy (--push-policy)
PUSH_COLUMNS = ("push_version", "push_accepted", "push_reason")


@dataclass(frozen=True)
class PushOutcome:
    """The node's answer to a push: ``accepted`` None when none came in time."""

    version: int
    accepted: bool | None
    reason: str = ""
    conflict: bool = False  # answers that contradict each other (a forger's among them)

    def describe(self) -> str:
        if self.conflict:
            return f"version {self.version}: {self.reason}"
        if self.accepted is None:
            return f"version {self.version}: no answer from a policy node ({self.reason})"
        return (f"version {self.version} " + ("accepted" if self.accepted
                                              else f"rejected: {self.reason}"))


# after a push's first answer, how long to listen for a contradicting one
CONFLICT_WAIT_S = 0.1


def push(lcm_url: str, prefix: str, message, timeout: float = 2.0,
         key: bytes | None = None) -> PushOutcome:
    """Publish ``message`` once on ``<prefix>POLICY`` and wait up to ``timeout``
    s for the node's answer on ``<prefix>POLICY_ACK`` (matched by version and
    utime; other answers and undecodable buffers are ignored). With ``key``
    the push is signed and only a signed answer counts (ftc.plant.signing)."""
    import lcm


    check_loopback_url(lcm_url)
    lc = lcm.LCM(lcm_url)
    answers: list = []

    auth = Auth(key) if key else None

    def on_ack(channel: str, data: bytes) -> None:
        if auth is not None and (data := auth.verify(channel, data)[0]) is None:
            return
        ack, _ = decode_ack(data)
        if ack is not None and (ack.version, ack.push_utime) == (message.version, message.utime):
            answers.append(ack)

    sub = lc.subscribe(prefix + "POLICY_ACK", on_ack)
    try:
        data = message.encode()
        lc.publish(prefix + "POLICY", auth.sign(prefix + "POLICY", data) if auth else data)
        deadline = time.monotonic() + timeout
        while not answers and time.monotonic() < deadline:
            lc.handle_timeout(max(1, int(1000 * (deadline - time.monotonic()))))
        # Without a key a neighbour that reads the push can answer it first; the
        # node's own answer follows within milliseconds: listen a little longer
        # for one that contradicts it.
        if answers:
            deadline = min(deadline, time.monotonic() + CONFLICT_WAIT_S)
        while answers and time.monotonic() < deadline:
            lc.handle_timeout(max(1, int(1000 * (deadline - time.monotonic()))))
    finally:
        lc.unsubscribe(sub)
    if not answers:
        return PushOutcome(message.version, None, f"nothing on {prefix}POLICY_ACK within "
                                                  f"{timeout:g} s")
    verdicts = {(bool(a.accepted), a.reason) for a in answers}
    if len(verdicts) > 1:
        said = "; ".join("accepted" if ok else f"rejected: {why}" for ok, why in sorted(verdicts))
        return PushOutcome(message.version, None,
                           f"conflicting answers on {prefix}POLICY_ACK ({said}): foreign traffic "
                           "on the bus (a bus key keeps it out: docs/deploy.md)", conflict=True)
    return PushOutcome(message.version, bool(answers[0].accepted), answers[0].reason)


def push_policy(policy, lcm_url: str, prefix: str, key: bytes | None = None) -> PushOutcome:
    """Push ``policy``'s actor (an ActorCritic) to the node on ``lcm_url``/``prefix``
    as the version of the time in milliseconds (above any earlier push and any
    file's), signed with ``key`` if given; returns the node's answer."""
    version = time.time_ns() // 1_000_000
    return push(lcm_url, prefix, policy_message(*actor_layers(policy), version=version),
                key=key)
