"""Bounded decoding of plant states on the Python side, as the C++ receivers
do it (cpp/plant/lcm/wire.h): a buffer's structure is checked against the
schema (lcmtypes/ftc/plant_state_t.lcm, in field order) before lcm-gen's
decoder sees it: the fingerprint, the array counts (non-negative, within the
bytes left) and the exact size. A refusal is a reason string, never an
exception, so a receiver counts it and carries on."""

from __future__ import annotations

import struct

from ftc.common.constants import NUM_ENGINES, NUM_TANKS

# utime, session, seq, command_seq (int64), episode, step (int32), age
# (double), operating_steps (int64): the fields before num_tanks
_STATE_HEAD = 8 * 4 + 4 + 4 + 8 + 8
# 4 booleans, 8 link counters, rate_hz, missed_ticks, watchdog_trips
_STATE_TAIL = 4 + 8 * 8 + 8 + 8 + 8


def check_state(data: bytes) -> str | None:
    """None if ``data`` is exactly one plant_state_t, else the reason."""
    from ftc.plant_state_t import plant_state_t

    fingerprint = plant_state_t._get_packed_fingerprint()
    if len(data) < 8:
        return f"{len(data)} bytes: shorter than a fingerprint"
    if data[:8] != fingerprint:
        return "not a plant_state_t (fingerprint)"
    at = 8 + _STATE_HEAD
    if len(data) < at + 2:
        return "truncated before num_tanks"
    tanks, engines = struct.unpack_from(">bb", data, at)
    if tanks < 0 or engines < 0:
        return f"num_tanks {tanks}, num_engines {engines} (allowed: 0..127)"
    expected = at + 2 + tanks * (8 + 8 + 1) + engines * 8 + _STATE_TAIL
    if len(data) != expected:
        return (f"{len(data)} bytes where num_tanks {tanks}, num_engines {engines} "
                f"make {expected}")
    return None


def decode_state(data: bytes):
    """(plant_state_t, None) or (None, the reason it was refused). A state
    must also have this plant's shape (NUM_TANKS tanks, NUM_ENGINES engines):
    a well-formed state of another shape is no state of this plant, and its
    arrays would not fit a receiver's (a 3-tank state made ftc.replay end in
    a traceback)."""
    from ftc.plant_state_t import plant_state_t

    why = check_state(data)
    if why is not None:
        return None, why
    try:
        msg = plant_state_t.decode(data)
    except (ValueError, struct.error) as e:  # not expected after the check
        return None, f"the decoder refused it: {e}"
    if (msg.num_tanks, msg.num_engines) != (NUM_TANKS, NUM_ENGINES):
        return None, (f"num_tanks {msg.num_tanks}, num_engines {msg.num_engines} "
                      f"(this plant has {NUM_TANKS} and {NUM_ENGINES})")
    return msg, None


def decode_ack(data: bytes):
    """(policy_ack_t, None) or (None, the reason it was refused): the fixed
    fields, then the reason string (int32 length with its NUL, at most
    MAX_REASON bytes), nothing after it."""
    from ftc.policy_ack_t import policy_ack_t

    head = 8 + 8 * 3 + 1 + 8
    if len(data) < head + 4 or data[:8] != policy_ack_t._get_packed_fingerprint():
        return None, "not a policy_ack_t (fingerprint or size)"
    (length,) = struct.unpack_from(">i", data, head)
    if not 1 <= length <= policy_ack_t.MAX_REASON + 1 or len(data) != head + 4 + length:
        return None, f"reason length {length} in {len(data)} bytes"
    try:
        return policy_ack_t.decode(data), None
    except (ValueError, struct.error, UnicodeDecodeError) as e:
        return None, f"the decoder refused it: {e}"
