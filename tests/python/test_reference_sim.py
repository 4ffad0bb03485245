"""The reference simulation (reference_sim.py) against cases solved by hand.

Each case is chosen so its solution is known in closed form: closed valves
(piecewise-linear levels, pumps innermost first), two tanks exchanging
through the conduit (exponential gap), a sink catching up with a pumping
source (tie, then the source leaves the group), a persistent tie, an empty
tank pinned by inflow smaller than its draw. Then conservation, symmetry,
the nominal reference figures of plant-model.md, degradation and the
episode / interval bookkeeping of the trajectory export.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.linalg import expm
from scipy.optimize import brentq

import reference_sim as ref

EXACT = 1e-9  # m: hand solutions vs the reference (integration at rtol 1e-10)
CLOSED = [0] * 6


def levels(**by_tank: float) -> np.ndarray:
    """Full tanks except the ones named t1..t6."""
    x = np.ones(6)
    for name, v in by_tank.items():
        x[int(name[1:]) - 1] = v
    return x


def valves(*open_tanks: int) -> list[int]:
    return [1 if i + 1 in open_tanks else 0 for i in range(6)]


# --------------------------------------------------------------------------- closed valves


def test_closed_valves_nominal_piecewise_linear_innermost_first() -> None:
    # d = 0.05 < p = 0.1: each wing drains its inner tank, then the middle, then the outer
    # one, at 0.05 m/s each; steps 1..20 empty tank 3 (and 4), 21..40 tank 2, 41..59 tank 1.
    p = ref.Params()
    x = np.ones(6)
    for n in range(1, 60):
        x = ref.integrate_step(x, CLOSED, p).x
        inner = max(0.0, 1 - 0.05 * n)
        middle = min(1.0, max(0.0, 1 - 0.05 * (n - 20)))
        outer = min(1.0, 1 - 0.05 * (n - 40))
        expected = [outer, middle, inner, inner, middle, outer]
        np.testing.assert_allclose(x, expected, atol=EXACT, err_msg=f"step {n}")


def test_closed_valves_weak_pumps_split_demand() -> None:
    # p = 0.03 < d = 0.05: tank 3 gives 0.03 and tank 2 the other 0.02 until tank 3 is
    # empty at t1 = 100/3 s (tank 2 then at 1/3); tank 2 gives 0.03 and tank 1 0.02 until
    # tank 2 is empty at t2 = t1 + 100/9 (tank 1 at 7/9); tank 1 then gives 0.03 and
    # 0.02 m^3/s goes unmet until t3 = t2 + (7/9)/0.03.
    p = ref.Params().copy(pump=[0.03] * 6)
    t1, t2 = 100 / 3, 100 / 3 + 100 / 9
    t3 = t2 + (7 / 9) / 0.03

    def wing(t: float) -> tuple[float, float, float, float]:
        """(tank1, tank2, tank3, unmet demand so far)."""
        if t <= t1:
            return 1.0, 1 - 0.02 * t, 1 - 0.03 * t, 0.0
        if t <= t2:
            return 1 - 0.02 * (t - t1), 1 / 3 - 0.03 * (t - t1), 0.0, 0.0
        if t <= t3:
            return 7 / 9 - 0.03 * (t - t2), 0.0, 0.0, 0.02 * (t - t2)
        return 0.0, 0.0, 0.0, 0.02 * (t3 - t2) + 0.05 * (t - t3)

    x = np.ones(6)
    unmet = 0.0
    for n in range(1, 80):
        res = ref.integrate_step(x, CLOSED, p)
        x, unmet = res.x, unmet + res.deficit[0]
        a, b, c, d = wing(float(n))
        np.testing.assert_allclose(x, [a, b, c, c, b, a], atol=EXACT, err_msg=f"step {n}")
        assert unmet == pytest.approx(d, abs=EXACT)
        assert res.deficit[1] == pytest.approx(res.deficit[0], abs=1e-12)


def test_tank_empties_mid_step_at_the_exact_time() -> None:
    # Tank 3 holds 0.0137 m: empty after 0.274 s; tank 2 serves the remaining 0.726 s.
    stats = ref.EventStats()
    res = ref.integrate_step(levels(t3=0.0137), CLOSED, ref.Params(), 1.0, stats)
    np.testing.assert_allclose(res.x, [1, 1 - 0.05 * 0.726, 0, 1 - 0.05, 1, 1], atol=EXACT)
    np.testing.assert_allclose(res.supplied, [0, 0.05 * 0.726, 0.0137, 0.05, 0, 0], atol=EXACT)
    assert stats.counts["empty"] == 1


# --------------------------------------------------------------------------- conduit


def test_two_open_tanks_exchange_exponentially_through_the_sinks_resistance() -> None:
    # Tanks 1 (source, 1 m) and 2 (sink, 0.5 m) open; tank 3 pumps, so neither of them does.
    # q = g e / R_2 with e = x1 - x2: de/dt = -2 g e / R_2, e = 0.5 exp(-0.1 t) for R_2 = 200.
    # The source's resistance does not limit the flow (plant-model.md), so R_1 = 50 is inert.
    p = ref.Params().copy(resistance=[50, 200, 100, 100, 100, 100])
    dt = 3.0
    res = ref.integrate_step(levels(t2=0.5), valves(1, 2), p, dt)
    e = 0.5 * math.exp(-0.1 * dt)
    np.testing.assert_allclose(res.x, [(1.5 + e) / 2, (1.5 - e) / 2, 1 - 0.05 * dt,
                                       1 - 0.05 * dt, 1, 1], atol=EXACT)


def test_equal_open_levels_exchange_nothing() -> None:
    res = ref.integrate_step(np.full(6, 0.7), valves(1, 2, 5, 6), ref.Params())
    np.testing.assert_allclose(res.x, [0.7, 0.7, 0.65, 0.65, 0.7, 0.7], atol=EXACT)


def test_sink_catches_up_with_pumping_source_then_roles_swap() -> None:
    # Tanks 2 (0.99 m, no pump draw: tank 3 serves E1) and 4 (1 m, pumping 0.05) open.
    # Gap e = x4 - x2: de/dt = -0.05 - 0.2 e, zero at t* = 5 ln(1.04). At the tie the group
    # {2, 4} would fall at rho = 0.025 < 0.05 = tank 4's own rate, so tank 4 leaves and
    # becomes the sink: e' = x2 - x4 = 0.25 (1 - exp(-0.2 (t - t*))). x2 + x4 = 1.99 - 0.05 t.
    stats = ref.EventStats()
    res = ref.integrate_step(levels(t2=0.99), valves(2, 4), ref.Params(), 1.0, stats)
    t_star = 5 * math.log(1.04)
    e2 = 0.25 * (1 - math.exp(-0.2 * (1 - t_star)))
    total = 1.99 - 0.05
    np.testing.assert_allclose(res.x, [1, (total + e2) / 2, 0.95, (total - e2) / 2, 1, 1],
                               atol=EXACT)
    assert stats.counts["join"] == 1
    assert stats.ties_formed == 0  # tank 4 left the group at once


def test_persistent_tie_then_member_leaves() -> None:
    # Tanks 2 and 4 full, tank 6 empty, all three open. Tank 6's pump draws nothing (tank 4
    # serves E2), so it fills from 0. Group {2, 4} falls at rho = (Q + 0.05) / 2 with
    # Q = 0.1 G, G = x_group - x6: tank 4 (own rate 0.05) stays while Q >= 0.05. G obeys
    # dG/dt = -1.5 Q - 0.025, G = (7/6) exp(-0.15 t) - 1/6, so tank 4 leaves at
    # t1 = ln(7/4) / 0.15. Afterwards the three tanks form an affine system (expm below).
    u = valves(2, 4, 6)
    x0 = levels(t6=0.0)
    t1 = math.log(7 / 4) / 0.15

    def before(t: float) -> tuple[float, float]:
        g = 7 / 6 * math.exp(-0.15 * t) - 1 / 6
        xg = (2 - 0.05 * t + g) / 3
        return xg, xg - g

    stats = ref.EventStats()
    res = ref.integrate_step(x0, u, ref.Params(), 3.0, stats)
    xg, x6 = before(3.0)
    np.testing.assert_allclose(res.x, [1, xg, 1 - 0.15, xg, 1, x6], atol=EXACT)
    assert stats.group_time == pytest.approx(3.0)

    # z = (x2, x4, x6, 1): q4 = 0.1 (x2 - x4), q6 = 0.1 (x2 - x6), tank 4 pumps 0.05.
    a = np.array([[-0.2, 0.1, 0.1, 0.0],
                  [0.1, -0.1, 0.0, -0.05],
                  [0.1, 0.0, -0.1, 0.0],
                  [0.0, 0.0, 0.0, 0.0]])
    xg, x6 = before(t1)
    dt = 8.0
    z = expm(a * (dt - t1)) @ np.array([xg, xg, x6, 1.0])
    stats = ref.EventStats()
    res = ref.integrate_step(x0, u, ref.Params(), dt, stats)
    np.testing.assert_allclose(res.x, [1, z[0], 1 - 0.05 * dt, z[1], 1, z[2]], atol=EXACT)
    assert stats.counts["leave"] == 1
    assert stats.group_time == pytest.approx(t1, abs=1e-9)


def test_empty_tank_with_small_inflow_stays_pinned_and_passes_it_on() -> None:
    # Tank 3 empty and open, tank 1 (0.4 m) open: inflow 0.1 x1 = 0.04 < 0.05 = tank 3's draw,
    # so tank 3 stays at 0 and pumps the inflow; tank 2 serves the rest.
    # x1 = 0.4 exp(-0.1 t); tank 3 supplies 0.4 (1 - exp(-0.1 t)) over t.
    dt = 2.0
    stats = ref.EventStats()
    res = ref.integrate_step(levels(t1=0.4, t3=0.0), valves(1, 3), ref.Params(), dt, stats)
    through = 0.4 * (1 - math.exp(-0.1 * dt))
    np.testing.assert_allclose(res.x, [0.4 * math.exp(-0.1 * dt), 1 - 0.05 * dt + through, 0,
                                       1 - 0.05 * dt, 1, 1], atol=EXACT)
    np.testing.assert_allclose(res.supplied[:3], [0, 0.05 * dt - through, through], atol=EXACT)
    assert stats.pinned_time == pytest.approx(dt)


def test_empty_tank_refills_then_empties_and_is_pinned() -> None:
    # As above with tank 1 at 0.6 m: inflow 0.06 > 0.05, tank 3 fills while pumping 0.05.
    # e = x1 - x3 obeys de/dt = 0.05 - 0.2 e: e = 0.25 + 0.35 exp(-0.2 t), and
    # x1 + x3 = 0.6 - 0.05 t. Tank 3 is back at 0 when 0.6 - 0.05 t = e(t) (about 3.5 s);
    # from then on its inflow 0.1 x1 < 0.05 pins it and x1 decays as exp(-0.1 t).
    def e(t: float) -> float:
        return 0.25 + 0.35 * math.exp(-0.2 * t)

    t_e = brentq(lambda t: 0.6 - 0.05 * t - e(t), 1.0, 6.0)
    x1_e = e(t_e)
    assert 0.1 * x1_e < 0.05
    for dt in (2.0, 6.0):
        stats = ref.EventStats()
        res = ref.integrate_step(levels(t1=0.6, t3=0.0), valves(1, 3), ref.Params(), dt, stats)
        if dt < t_e:
            x1, x3 = (0.6 - 0.05 * dt + e(dt)) / 2, (0.6 - 0.05 * dt - e(dt)) / 2
            x2 = 1.0
        else:
            x1, x3 = x1_e * math.exp(-0.1 * (dt - t_e)), 0.0
            x2 = 1 - (0.05 * (dt - t_e) - (x1_e - x1))
        np.testing.assert_allclose(res.x[:3], [x1, x2, x3], atol=EXACT, err_msg=f"dt {dt}")
        if dt > t_e:
            assert stats.counts["empty"] == 1
            assert stats.refill_time == pytest.approx(t_e, abs=1e-9)
            assert stats.pinned_time == pytest.approx(dt - t_e, abs=1e-9)


# --------------------------------------------------------------------------- invariants


def random_case(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, ref.Params]:
    x = rng.uniform(0, 1, 6) * (rng.uniform(size=6) > 0.2)  # some tanks empty
    u = rng.integers(0, 2, 6)
    p = ref.degraded_params(rng.uniform(5, 30, 6), rng.uniform(5, 30, 2), rng.integers(0, 10))
    return x, u, p


def test_conservation_volume_drop_equals_supply_and_supply_plus_deficit_is_demand() -> None:
    rng = np.random.default_rng(7)
    for _ in range(40):
        x, u, p = random_case(rng)
        res = ref.integrate_step(x, u, p)
        assert np.sum(x) - np.sum(res.x) == pytest.approx(np.sum(res.supplied), abs=1e-9)
        wing = [res.supplied[:3].sum(), res.supplied[3:].sum()]
        np.testing.assert_allclose(np.add(wing, res.deficit), p.demand, atol=1e-9)
        assert np.all(res.x >= 0) and np.all(res.x <= 1)
        assert np.all(res.supplied <= p.pump + 1e-12)


def test_mirror_symmetry() -> None:
    # Swapping the wings (tank i <-> 7 - i, engine 1 <-> 2) mirrors the solution.
    rng = np.random.default_rng(11)
    for _ in range(15):
        x, u, p = random_case(rng)
        mirrored = p.copy(pump=p.pump[::-1], resistance=p.resistance[::-1], demand=p.demand[::-1])
        a = ref.integrate_step(x, u, p).x
        b = ref.integrate_step(x[::-1], u[::-1], mirrored).x
        np.testing.assert_allclose(a, b[::-1], atol=1e-9)


def test_step_of_dt_equals_two_half_steps() -> None:
    rng = np.random.default_rng(3)
    for _ in range(15):
        x, u, p = random_case(rng)
        whole = ref.integrate_step(x, u, p, 1.0).x
        half = ref.integrate_step(ref.integrate_step(x, u, p, 0.5).x, u, p, 0.5).x
        np.testing.assert_allclose(whole, half, atol=1e-9)


# --------------------------------------------------------------------------- episodes


@pytest.mark.parametrize("u, mean_reward", [(CLOSED, 2.690), ([1] * 6, 1.393)])
def test_nominal_episodes_last_59_steps_with_the_reference_rewards(u, mean_reward) -> None:
    ep = ref.episode(ref.Params(), np.array(u))
    assert ep.terminal and len(ep.rewards) == 59
    assert ep.rewards.mean() == pytest.approx(mean_reward, abs=0.005)
    assert not np.any(ep.deficit > 1e-9)


def test_reward_by_hand() -> None:
    full = ref.reward(np.ones(6), CLOSED)
    assert full["cg"] == 0 and full["spread"] == pytest.approx(math.sqrt(14 / 3))
    # Only tanks 1 and 6 half full, tank 4 full, two valves open: w = (.5,0,0,1,0,.5),
    # W = 2, cg = (-1.5 + 1 + 1.5) / 2 = 0.5, var = (.5*12.25 + 0.25 + .5*6.25) / 2 = 4.75.
    r = ref.reward([0.5, 0, 0, 1, 0, 0.5], [1, 0, 0, 0, 0, 1])
    assert r["cg"] == pytest.approx(0.5)
    assert r["spread"] == pytest.approx(math.sqrt(4.75))
    assert r["reward"] == pytest.approx((1 - 0.5 / 3) * math.sqrt(4.75) - 1 / 3)
    assert ref.reward(np.zeros(6), [1] * 6)["reward"] == -1.0


def test_degraded_parameters() -> None:
    # plant-model.md: D = 20 at age 9 gives 55 % pump, 145 % resistance, 145 % demand.
    inf = math.inf
    p = ref.degraded_params([inf, inf, inf, inf, 20, 20], [20, inf], 9)
    np.testing.assert_allclose(p.pump, [0.1] * 4 + [0.055] * 2)
    np.testing.assert_allclose(p.resistance, [100] * 4 + [145] * 2)
    np.testing.assert_allclose(p.demand, [0.0725, 0.05])
    assert ref.degraded_params([5] * 6, [inf] * 2, 9).pump.tolist() == [0.0] * 6


def test_simulate_counts_steps_ages_and_cuts_episodes_at_interval_boundaries() -> None:
    # Closed valves, nominal, 100-step intervals: episode 0 ends terminal after 59 steps,
    # episode 1 is cut after 41 steps at the boundary, episode 2 starts full at age 1.
    traj = ref.simulate({}, np.zeros((130, 6), dtype=int), steps_per_interval=100)
    assert traj.step[58] == 59 and traj.terminal[58] and not traj.truncated[58]
    assert traj.episode[59] == 1 and traj.step[59] == 1
    assert traj.step[99] == 41 and traj.truncated[99] and not traj.terminal[99]
    assert traj.episode[100] == 2 and traj.step[100] == 1 and traj.age[100] == 1.0
    assert np.all(traj.age[:100] == 0)
    np.testing.assert_allclose(traj.levels[100], [1, 1, 0.95, 0.95, 1, 1], atol=EXACT)
    np.testing.assert_allclose(traj.levels[59], traj.levels[0], atol=EXACT)
    row = traj.rows()[100]
    assert row[:3] == [2, 1, 1.0] and len(row) == 15


def test_simulate_degrades_stepwise_per_interval() -> None:
    # Engine 1 with D_E = 2: demand 0.05 (1 + a/2); the inner tank 3 drains at that rate.
    inf = math.inf
    traj = ref.simulate({"engine_factor": [2.0, inf]}, np.zeros((25, 6), dtype=int),
                        steps_per_interval=10)
    for k in (0, 10, 20):
        a = k // 10
        assert traj.age[k] == a
        assert traj.levels[k][2] == pytest.approx(1 - 0.05 * (1 + a / 2), abs=EXACT)
