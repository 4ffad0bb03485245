"""Hypothesis property tests: LCM message round trips (all three types) and
the reward (bounds, mirror symmetry, scale invariance, torch == numpy ==
C++, the empty plant). Each property runs a bounded number of examples so
the whole file stays within a few seconds.

Reward bounds (plant-model.md, "Reward"): r = (1 - |cg|/3) sigma - u_bar
with the tank arms m in [-3, 3]. sigma is the standard deviation of a
distribution on [-3, 3] with mean cg, so sigma^2 <= (3 - cg)(3 + cg) =
9 - cg^2 (Bhatia-Davis), and (1 - |cg|/3) sqrt(9 - cg^2) <= 3 with equality
at cg = 0: only tanks 1 and 6 holding equal fuel. Hence

    -u_bar <= r <= 3 - u_bar,   so  -1 <= r <= 3,

and the full plant (all levels equal) gives exactly sqrt(14/3) - u_bar,
since the arms' mean square is (9 + 4 + 1) / 3. sqrt(14/3) is not an upper
bound: emptying the inner tanks raises the spread.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ftc.plant_control_t import plant_control_t
from ftc.plant_state_t import plant_state_t
from ftc.common.constants import EMPTY_VOLUME
from ftc.plant.reward import reward, reward_terms, reward_torch
from ftc.valve_command_t import valve_command_t

FAST = settings(max_examples=200, deadline=None)

i64 = st.integers(-(2 ** 63), 2 ** 63 - 1)
i32 = st.integers(-(2 ** 31), 2 ** 31 - 1)
i8 = st.integers(-128, 127)
f64 = st.floats(allow_nan=True, allow_infinity=True, width=64)
levels = st.lists(st.floats(0.0, 1.0), min_size=6, max_size=6).map(np.array)
valves = st.lists(st.integers(0, 1), min_size=6, max_size=6).map(np.array)


def _same_float(a: float, b: float) -> bool:
    return (math.isnan(a) and math.isnan(b)) or a == b


# ---------------------------------------------------------------------------
# LCM messages
# ---------------------------------------------------------------------------

@st.composite
def state_messages(draw) -> plant_state_t:
    m = plant_state_t()
    m.utime, m.seq, m.command_seq, m.operating_steps = (draw(i64) for _ in range(4))
    m.session, m.other_session = draw(i64), draw(i64)
    m.episode, m.step = draw(i32), draw(i32)
    m.age = draw(f64)
    m.num_tanks, m.num_engines = draw(st.integers(0, 8)), draw(st.integers(0, 3))
    m.level = draw(st.lists(f64, min_size=m.num_tanks, max_size=m.num_tanks))
    m.true_level = draw(st.lists(f64, min_size=m.num_tanks, max_size=m.num_tanks))
    m.valve = draw(st.lists(i8, min_size=m.num_tanks, max_size=m.num_tanks))
    m.deficit = draw(st.lists(f64, min_size=m.num_engines, max_size=m.num_engines))
    m.terminal, m.truncated, m.evaluation, m.watchdog_tripped = (draw(st.booleans())
                                                                 for _ in range(4))
    m.duplicate_commands, m.stale_commands, m.rejected_commands, m.decode_errors = (
        draw(i64) for _ in range(4))
    return m


@st.composite
def command_messages(draw) -> valve_command_t:
    m = valve_command_t()
    m.utime, m.seq, m.state_seq, m.session = draw(i64), draw(i64), draw(i64), draw(i64)
    m.num_valves = draw(st.integers(0, 127))
    m.valve = draw(st.lists(i8, min_size=m.num_valves, max_size=m.num_valves))
    return m


@st.composite
def control_messages(draw) -> plant_control_t:
    m = plant_control_t()
    m.utime, m.seq, m.command = draw(i64), draw(i64), draw(i8)
    m.session, m.operating_step = draw(i64), draw(i64)
    return m


@FAST
@given(state_messages())
def test_plant_state_round_trip(m):
    data = m.encode()
    d = plant_state_t.decode(data)
    from ftc.plant.wire import check_state

    assert check_state(data) is None  # the receivers' bounded check passes every real state
    for name in ("utime", "session", "other_session", "seq", "command_seq", "episode", "step",
                 "operating_steps",
                 "num_tanks", "num_engines", "terminal", "truncated", "evaluation",
                 "watchdog_tripped", "duplicate_commands", "stale_commands",
                 "rejected_commands", "decode_errors"):
        assert getattr(d, name) == getattr(m, name), name
    assert _same_float(d.age, m.age)
    for name in ("level", "true_level", "deficit"):
        assert len(getattr(d, name)) == len(getattr(m, name))
        assert all(_same_float(a, b) for a, b in zip(getattr(d, name), getattr(m, name))), name
    assert list(d.valve) == list(m.valve)
    assert d.encode() == data  # canonical: decoding and encoding again is the identity


@FAST
@given(command_messages())
def test_valve_command_round_trip(m):
    data = m.encode()
    d = valve_command_t.decode(data)
    assert (d.utime, d.session, d.seq, d.state_seq, d.num_valves) == (
        m.utime, m.session, m.seq, m.state_seq, m.num_valves)
    assert list(d.valve) == list(m.valve)
    assert d.encode() == data


@FAST
@given(control_messages())
def test_plant_control_round_trip(m):
    data = m.encode()
    d = plant_control_t.decode(data)
    assert (d.utime, d.session, d.seq, d.command, d.operating_step) == (
        m.utime, m.session, m.seq, m.command, m.operating_step)
    assert d.encode() == data


@FAST
@given(st.one_of(state_messages(), command_messages(), control_messages()), st.data())
def test_a_truncated_message_never_decodes(m, data):
    # A short read must be an error, never a message with made-up fields.
    encoded = m.encode()
    cut = data.draw(st.integers(0, len(encoded) - 1))
    with pytest.raises(Exception):
        type(m).decode(encoded[:cut])


@FAST
@given(st.one_of(state_messages(), command_messages(), control_messages()))
def test_a_message_never_decodes_as_another_type(m):
    # The fingerprint (first 8 bytes) tells the types apart.
    for other in (plant_state_t, valve_command_t, plant_control_t):
        if other is not type(m):
            with pytest.raises(ValueError):
                other.decode(m.encode())


# ---------------------------------------------------------------------------
# Reward
# ---------------------------------------------------------------------------

@FAST
@given(levels, valves)
def test_reward_bounds(x, u):
    t = reward_terms(x, u)
    r, u_bar = float(t.reward), float(np.mean(u))
    assert -u_bar - 1e-12 <= r <= 3.0 - u_bar + 1e-12
    assert -1.0 <= r <= 3.0
    cg = float(t.cg)
    assert -3.0 - 1e-12 <= cg <= 3.0 + 1e-12  # a rounding ulp past the arm
    assert 0.0 <= float(t.spread) <= math.sqrt(max(9.0 - cg * cg, 0.0)) + 1e-6


def test_reward_bound_3_is_attained_and_full_tanks_give_sqrt_14_3():
    assert float(reward(np.array([1.0, 0, 0, 0, 0, 1.0]), np.zeros(6))) == pytest.approx(3.0)
    assert float(reward(np.ones(6), np.zeros(6))) == pytest.approx(math.sqrt(14 / 3))
    assert float(reward(np.ones(6), np.ones(6))) == pytest.approx(math.sqrt(14 / 3) - 1)


@FAST
@given(levels, valves)
def test_reward_is_mirror_symmetric(x, u):
    # Tank i <-> tank 7-i negates every arm: cg changes sign, |cg| and sigma do not.
    assert float(reward(x[::-1], u[::-1])) == pytest.approx(float(reward(x, u)), abs=1e-12)
    assert float(reward_terms(x[::-1], u).cg) == pytest.approx(-float(reward_terms(x, u).cg),
                                                                abs=1e-12)


@FAST
@given(levels, valves, st.floats(1e-3, 1e3))
def test_reward_is_scale_invariant(x, u, k):
    # cg and sigma are ratios of fuel masses: scaling every level leaves them be.
    if x.sum() * min(k, 1.0) < 10 * EMPTY_VOLUME:
        return
    assert float(reward(k * x, u)) == pytest.approx(float(reward(x, u)), rel=1e-9, abs=1e-12)


@FAST
@given(st.lists(st.floats(-0.5, 1.5), min_size=6, max_size=6).map(np.array), valves)
def test_negative_levels_count_as_empty(x, u):
    assert float(reward(x, u)) == float(reward(np.maximum(x, 0.0), u))


@FAST
@given(valves, st.floats(0.0, EMPTY_VOLUME / 6.5))
def test_empty_plant_reward_is_minus_activity(u, level):
    t = reward_terms(np.full(6, level), u)
    assert (float(t.cg), float(t.spread)) == (0.0, 0.0)
    assert float(t.reward) == -float(np.mean(u))


@settings(max_examples=50, deadline=None)
@given(st.lists(st.lists(st.floats(0.0, 1.0), min_size=6, max_size=6), min_size=1,
                max_size=16).map(np.array),
       st.data())
def test_reward_torch_equals_numpy_on_batches(x, data):
    import torch

    u = np.array(data.draw(st.lists(st.lists(st.integers(0, 1), min_size=6, max_size=6),
                                    min_size=len(x), max_size=len(x))))
    r_np = reward(x, u)
    r_t = reward_torch(torch.as_tensor(x, dtype=torch.float64), torch.as_tensor(u))
    np.testing.assert_allclose(r_t.numpy(), r_np, rtol=1e-12, atol=1e-12)
    for i in range(len(x)):  # a batch is the rows one by one
        assert float(reward(x[i], u[i])) == pytest.approx(float(r_np[i]), abs=1e-15)


@FAST
@given(levels, valves)
def test_reward_python_equals_cpp_core(x, u):
    from ftc import _core

    c = _core.reward(x, u.astype(np.int32))
    t = reward_terms(x, u)
    assert c["reward"] == pytest.approx(float(t.reward), abs=1e-12)
    assert c["cg"] == pytest.approx(float(t.cg), abs=1e-12)
    assert c["spread"] == pytest.approx(float(t.spread), abs=1e-12)


# ---------------------------------------------------------------------------
# Scenario text through the core's parser (the fuzz target's property, in
# Python): parses or raises ScenarioError, never anything else.
# ---------------------------------------------------------------------------

_values = st.one_of(f64.map(repr),  # repr gives TOML's nan, inf, -inf too
                    st.integers(-2 ** 40, 2 ** 40).map(str), st.booleans().map(lambda b: str(b).lower()),
                    st.text(max_size=8).map(lambda s: '"' + s.replace('"', "").replace("\\", "")
                                            + '"'),
                    st.lists(st.floats(-10, 1e300) | st.just(float("inf")), max_size=8)
                    .map(lambda v: "[" + ", ".join(repr(a) for a in v) + "]"))
_keys = st.sampled_from(["name", "tank_factor", "engine_factor", "degradation",
                         "steps_per_interval", "noise", "start", "bogus"])


@FAST
@given(st.lists(st.tuples(_keys, _values), max_size=4, unique_by=lambda kv: kv[0]))
def test_scenario_text_parses_or_names_the_key(pairs):
    from ftc import _core

    text = "\n".join(f"{k} = {v}" for k, v in pairs) + "\n"
    try:
        s = _core.parse_scenario(text, "prop.toml")
    except _core.ScenarioError as e:
        msg = str(e)
        assert msg.startswith("prop.toml") and "\n" not in msg.strip()
        return
    assert s.steps_per_interval > 0
