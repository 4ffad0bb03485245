// Closed-form steps with the conduit active (linear_step.h): an analytic case,
// CVODE at tight tolerances on random states (events included), the hand-over
// to CVODE where a tank is pinned, and batch rollouts with the option on.
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <vector>

#include "plant/core/degradation.h"
#include "plant/core/linear_step.h"
#include "plant/core/rollout.h"

namespace ftc {
namespace {

Valves FromCode(int code) {
  Valves u;
  for (int i = 0; i < kTanks; ++i) u[i] = (code >> i) & 1;
  return u;
}

TEST(LinearConduitStep, AMemberThatLeavesATiedGroupAtTheStartRejoinsIt) {
  // Full tanks, all open ones tied. A member whose pump draws more than its share
  // of the group's rate while the sinks' inflow is still 0 leaves the group at
  // t = 0, then rejoins it as the inflow grows (its root, the leave condition,
  // falls to 0): the two end the step tied, as CVODE and the independent
  // reference simulation (tests/python/reference_sim.py) give them (0.99887458
  // and 0.99361839). A closed form that missed the rejoin let the member rise
  // past the group: a split of 2e-3 and 7e-5 m.
  struct Case {
    int code;
    Vec6 resistance, pump;
    Vec2 demand;
  };
  Case cases[2];
  cases[0].code = 0b000111;
  cases[0].resistance << 130.3997568, 100, 136.90377341, 100, 100, 100;
  cases[0].pump << 0.06960024, 0.1, 0.06309623, 0.1, 0.1, 0.1;
  cases[0].demand << 0.06312508, 0.05;
  cases[1].code = 0b011110;
  cases[1].resistance << 100, 100, 100, 130.81528438, 124.895085, 100;
  cases[1].pump << 0.1, 0.1, 0.1, 0.06918472, 0.07510492, 0.1;
  cases[1].demand << 0.10644251, 0.05;
  for (const Case& c : cases) {
    PlantParams p;
    p.resistance = c.resistance;
    p.pump = c.pump;
    p.demand = c.demand;
    const Valves u = FromCode(c.code);
    const LinearStepResult closed = LinearConduitStep(Vec6::Ones(), u, p, 1.0);
    StepIntegrator cvode;
    const StepResult reference = cvode.Step(Vec6::Ones(), u, p, 1.0);
    ASSERT_EQ(closed.t, 1.0);
    // CVODE's tolerance (2.5e-8 m per step measured, integrator.cpp), with margin
    EXPECT_LT((closed.x - reference.x).cwiseAbs().maxCoeff(), 1e-7) << "valves " << c.code;
  }
}

TEST(LinearConduitStep, AMemberThatLeavesATieFromOneUlpAboveItRejoinsIt) {
  // Tanks 1, 2 and 5 open; tanks 1 and 5 tied at 0.5, tank 5 one ulp above, at
  // or one ulp below tank 1 (where a located root leaves a tie). Tank 5 draws
  // 0.02 (E2's demand after tank 4's 0.03), tank 1 nothing, and tank 2, a sink
  // 0.2 - rise below, receives q2 = 0.1 (0.2 - rise) < 0.02: tank 5 leaves the
  // pair at once, and rejoins it when q2, growing at ~1e-3 m^3/s^2, passes its
  // draw, after a dip of 0.005 rise^2 (below 1e-8 m; test_integrator.cpp's
  // family). The exact solution ends the step tied; the closed form rejoins at
  // the dip's bottom where it is within the tie tolerance (1e-9 m), and CVODE
  // agrees. One ulp above, a rejoin root that was the gap x1 - x5 started
  // below 0, was never watched, and tank 5 ended 4.4e-4 m above tank 1.
  PlantParams p;
  p.pump[3] = 0.03;
  const Valves u = FromCode(0b010011);
  for (const double rise : {2e-6, 5e-6, 1e-5, 2e-5, 5e-5}) {
    for (const double x5 : {std::nextafter(0.5, 1.0), 0.5, std::nextafter(0.5, 0.0)}) {
      Vec6 x0;
      x0 << 0.5, 0.3 + rise, 0.0, 0.8, x5, 0.8;
      const LinearStepResult closed = LinearConduitStep(x0, u, p, 1.0);
      ASSERT_EQ(closed.t, 1.0);
      EXPECT_LE(std::abs(closed.x[4] - closed.x[0]), 1e-9) << "rise " << rise;
      StepIntegrator cvode;
      const StepResult reference = cvode.Step(x0, u, p, 1.0);
      // CVODE's tolerance (2.5e-8 m per step measured, integrator.cpp), with margin
      EXPECT_LT((closed.x - reference.x).cwiseAbs().maxCoeff(), 1e-7) << "rise " << rise;
    }
  }
}

TEST(LinearConduitStep, TwoTanksLevelOutExponentially) {
  // No pumps, no demand, tanks 1 and 2 open (areas 1 and 2): the difference
  // d = x1 - x2 obeys d' = -(g / R)(1 / c1 + 1 / c2) d, and the volume
  // c1 x1 + c2 x2 is kept. Closed form against closed form: rounding only.
  PlantParams p;
  p.pump.setZero();
  p.demand.setZero();
  p.area[1] = 2.0;
  Vec6 x0;
  x0 << 0.9, 0.3, 0.5, 0.5, 0.5, 0.5;
  const LinearStepResult r = LinearConduitStep(x0, FromCode(0b000011), p, 1.0);
  const double k = p.g / p.resistance[0] * (1.0 / p.area[0] + 1.0 / p.area[1]);
  const double d = 0.6 * std::exp(-k * 1.0);
  const double volume = p.area[0] * x0[0] + p.area[1] * x0[1];
  EXPECT_EQ(r.t, 1.0);
  EXPECT_EQ(r.events, 0);
  EXPECT_NEAR(r.x[0] - r.x[1], d, 1e-14);
  EXPECT_NEAR(p.area[0] * r.x[0] + p.area[1] * r.x[1], volume, 1e-14);
  for (int i = 2; i < kTanks; ++i) EXPECT_EQ(r.x[i], 0.5);  // closed, no pumps: still
}

TEST(LinearConduitStep, MatchesTightCvodeOnRandomStatesIncludingEvents) {
  // Random levels (a sixth of them empty), valves and ages of a fault with a
  // dead pump: tanks run dry, sinks join the group, members leave it within
  // the step. CVODE at rtol 1e-12 is within ~1e-11 m of the exact solution;
  // measured worst 7e-12 over 60,000 such steps, so 1e-9 leaves a margin while
  // an error in a root's location (~1e-3 m) or in a mode (~1e-2) would fail.
  FaultScenario s;
  s.engine_factor[0] = 20.0;
  s.tank_factor[2] = 6.0;
  IntegratorOptions tight;
  tight.rtol = 1e-12;
  tight.atol = 1e-14;
  StepIntegrator reference(tight);
  StepIntegrator rest(tight);
  std::mt19937_64 rng(11);
  std::uniform_real_distribution<double> level(0.0, 1.0);
  int events = 0;
  for (int n = 0; n < 3000; ++n) {
    const PlantParams p = DegradedParams(PlantParams{}, s, 9.0 * level(rng));
    Vec6 x;
    for (int i = 0; i < kTanks; ++i) x[i] = level(rng) < 1.0 / 6 ? 0.0 : level(rng);
    int code = static_cast<int>(rng() % 64);
    if (__builtin_popcount(code) < 2) code |= 0b010100;
    const Valves u = FromCode(code);
    const LinearStepResult exact = LinearConduitStep(x, u, p, 1.0);
    Vec6 end = exact.x;
    if (exact.t < 1.0)  // a mode it does not handle: CVODE does the rest, as BatchRollout does
      end = rest.Step(exact.x, u, p, 1.0 - exact.t).x;
    events += exact.events;
    const Vec6 cvode = reference.Step(x, u, p, 1.0).x;
    ASSERT_LT((end - cvode).cwiseAbs().maxCoeff(), 1e-9)
        << "step " << n << " valves " << code << " from " << x.transpose();
  }
  EXPECT_GT(events, 300);  // the events were exercised
}

TEST(LinearStepper, AModesPreparationServesAnyStateAndAnyStepper) {
  // A planner's held action: 6 steps with the same valves from one stepper
  // against a fresh one per step. A mode's preparation is made at the levels 0,
  // whichever state first meets the mode, and shared through the thread's
  // cache, so the two are equal bit for bit (were it made at the state that
  // met it, they would differ by rounding, ~1e-16).
  FaultScenario s;
  s.engine_factor[1] = 20.0;
  const PlantParams p = DegradedParams(PlantParams{}, s, 6.0);
  const Valves u = FromCode(0b011011);
  Vec6 kept, fresh;
  kept << 0.9, 0.2, 0.6, 0.4, 0.8, 0.3;
  fresh = kept;
  LinearStepper stepper;
  for (int t = 0; t < 6; ++t) {
    kept = stepper.Step(kept, u, p, 1.0).x;
    fresh = LinearConduitStep(fresh, u, p, 1.0).x;
    EXPECT_EQ(kept, fresh) << "step " << t;
  }
  EXPECT_GT((kept - Vec6(0.9, 0.2, 0.6, 0.4, 0.8, 0.3)).cwiseAbs().maxCoeff(), 0.1);  // it moved
}

TEST(LinearStepper, ResultsDoNotDependOnWhatTheThreadsCacheHolds) {
  // One trajectory of random valves (events included) stepped twice: alone, and
  // with every step preceded by steps of 40 other parameter sets from other
  // states, which fill the thread's cache of preparations (4,096 entries) past
  // its size, so the trajectory's modes are evicted and made again or found as
  // another state left them. The two runs must be equal bit for bit.
  FaultScenario s;
  s.engine_factor[0] = 20.0;
  s.tank_factor[4] = 15.0;
  auto run = [&](bool flood) {
    std::mt19937_64 rng(3), noise(4);
    Vec6 x;
    x << 1.0, 0.7, 0.9, 0.95, 0.6, 0.8;
    std::vector<Vec6> path;
    int events = 0;
    for (int t = 0; t < 300; ++t) {
      const PlantParams p = DegradedParams(PlantParams{}, s, t / 64);
      if (flood) {
        for (int k = 0; k < 40; ++k) {
          Vec6 y = Vec6::Constant(0.5) + 0.5 * Vec6::Random();
          const Valves v = FromCode(static_cast<int>(noise() % 64));
          LinearConduitStep(y, v, DegradedParams(PlantParams{}, s, 0.01 * (k + 40 * t)), 1.0);
        }
      }
      const Valves u = FromCode(static_cast<int>(rng() % 64));
      LinearStepper stepper;
      const LinearStepResult r = stepper.Step(x, u, p, 1.0);
      events += r.events;  // (r.t < 1: handed over to CVODE; the test goes on from r.x)
      x = r.x;
      path.push_back(x);
      if (x.sum() < 1.0) x = Vec6::Ones();  // refill
    }
    return std::make_pair(path, events);
  };
  const auto alone = run(false), flooded = run(true);
  ASSERT_GT(alone.first.size(), 100u);
  EXPECT_GT(alone.second, 10);  // mode switches within steps were located
  ASSERT_EQ(alone.first.size(), flooded.first.size());
  for (std::size_t t = 0; t < alone.first.size(); ++t)
    ASSERT_EQ(alone.first[t], flooded.first[t]) << "step " << t;
}

TEST(LinearConduitStep, TwoDrivenTanksAreNotGivenOneEigenvector) {
  // The suite's random-01 at age 3 (tank 3 worn): tanks 3 and 4 empty, pinned,
  // each passing its inflow to its engine, so the pumps of tanks 2 and 5 after
  // them are driven by the group level: M has the eigenvalue 0 twice, and the
  // eigensolver returned one eigenvector for both (6e-3 m off in tank 2 after
  // the step). The closed form must refuse that basis (the rest of the step is
  // CVODE's) and end within CVODE's tolerance of tight CVODE (2.5e-8 m a step
  // at the plant's rtol 1e-8: integrator.cpp; 1e-7 leaves a margin).
  PlantParams p;
  p.resistance[2] = 122.9585979949491;  // the values of that step, to the last digit
  p.pump[2] = 0.0770414020050509;
  p.demand[1] = 0.0621231714216439;
  Vec6 x0;
  x0 << 0.4829116196287325, 0.2260881336896958, 0.0, 0.0, 0.178493799489727, 0.40333324748281074;
  const Valves u = FromCode(0b101101);
  IntegratorOptions tight;
  tight.rtol = 1e-12;
  tight.atol = 1e-14;
  const Vec6 reference = StepIntegrator(tight).Step(x0, u, p, 1.0).x;
  const LinearStepResult r = LinearConduitStep(x0, u, p, 1.0);
  Vec6 x = r.x;
  if (r.t < 1.0) x = StepIntegrator().Step(r.x, u, p, 1.0 - r.t).x;
  EXPECT_LT((x - reference).cwiseAbs().maxCoeff(), 1e-7);
}

TEST(LinearConduitStep, APinnedTankAndTheTankItDrivesAreExact) {
  // Tank 3 empty and open below full tanks 1 and 2, R_3 = 1000: its inflow
  // g (1 - 0) / R_3 = 0.01 m^3/s is below its pump's draw (min(0.1, demand
  // 0.05) = 0.05), so it is pinned, passing the inflow to engine 1; tank 2
  // leaves the group and draws the rest, 0.05 - inflow, which moves with the
  // group level (M is not a symmetric star: the general eigendecomposition).
  // Against CVODE at rtol 1e-12, as in the random states above.
  PlantParams p;
  p.resistance[2] = 1000.0;
  Vec6 x0;
  x0 << 1.0, 1.0, 0.0, 1.0, 1.0, 1.0;
  const Valves u = FromCode(0b000111);
  const LinearStepResult r = LinearConduitStep(x0, u, p, 1.0);
  IntegratorOptions tight;
  tight.rtol = 1e-12;
  tight.atol = 1e-14;
  StepIntegrator reference(tight);
  EXPECT_EQ(r.t, 1.0);
  EXPECT_LT((r.x - reference.Step(x0, u, p, 1.0).x).cwiseAbs().maxCoeff(), 1e-9);
  EXPECT_EQ(r.x[2], 0.0);
}

TEST(LinearConduitStep, HandsOverWhereAPumpAfterAPinnedTankCannotCoverItsEngine) {
  // As above with engine 1's demand 0.15 > the pumps' 0.1: tank 2's draw is
  // min(0.1, 0.15 - inflow), which has a kink: the closed form stops at t = 0
  // and leaves the levels as they were, for CVODE.
  PlantParams p;
  p.resistance[2] = 1000.0;
  p.demand[0] = 0.15;
  Vec6 x0;
  x0 << 1.0, 1.0, 0.0, 1.0, 1.0, 1.0;
  const LinearStepResult r = LinearConduitStep(x0, FromCode(0b000111), p, 1.0);
  EXPECT_EQ(r.t, 0.0);
  EXPECT_EQ(r.x, x0);
}

TEST(LinearConduitStep, RisingOffTheBottomByLessThanTheToleranceIsExact) {
  // test_integrator.cpp's grazing cases where the closed form handles the mode:
  // an empty tank whose inflow exceeds its draw by 0.1 eps or 0.2 eps m^3/s
  // (eps from 1e-14 to 1e-4 m) rises by ~eps^2 m and returns. The closed
  // form's levels are exact to rounding, so it samples the level roots only at
  // levels >= 0, where they are the bare levels (dynamics.cpp); it must locate
  // the return once and end where tight CVODE ends.
  IntegratorOptions tight;
  tight.rtol = 1e-12;
  tight.atol = 1e-14;
  std::mt19937_64 rng(3);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  for (int k = 0; k < 400; ++k) {
    const double eps = std::pow(10.0, -14 + 10 * unit(rng)) * (k % 4 < 2 ? 1 : -1);
    PlantParams p;
    Vec6 x = Vec6::Zero();
    x[0] = 0.5 + eps;
    int code = 0b001001;  // tank 4 fed by tank 1
    if (k % 2 == 1) {     // tank 3 pinned, tank 2 draws 0.1 - 0.1 x1, tank 1 the rest
      p.demand[0] = 0.1;
      code = 0b000111;
    }
    const Valves u = FromCode(code);
    LinearStepResult r;
    ASSERT_NO_THROW(r = LinearConduitStep(x, u, p, 1.0)) << "case " << k << " eps " << eps;
    ASSERT_EQ(r.t, 1.0) << k;
    EXPECT_LE(r.events, 2) << k;
    StepIntegrator reference(tight);
    EXPECT_LT((r.x - reference.Step(x, u, p, 1.0).x).cwiseAbs().maxCoeff(), 1e-9) << k;
  }
}

TEST(BatchRollout, ClosedFormActiveStepsAgreeWithCvodeRollouts) {
  // The planner's batch (64 settings held 3 steps, then closed) from a mid-
  // episode state: totals within CVODE's own error at the plant's tolerances
  // (1e-8 relative per step, summed over 10 steps of rewards of order 1).
  FaultScenario s;
  s.tank_factor[4] = 6.0;
  const PlantParams p = DegradedParams(PlantParams{}, s, 7.0);
  Vec6 x0;
  x0 << 0.2, 0.35, 0.0, 0.6, 0.7, 0.05;
  std::vector<Valves> seq;
  for (int a = 0; a < 64; ++a)
    for (int t = 0; t < 10; ++t) seq.push_back(t < 3 ? FromCode(a) : Valves::Zero());
  RolloutOptions exact_options;
  exact_options.exact_active_conduit = true;
  BatchRollout exact({}, exact_options);
  BatchRollout cvode;
  const RolloutResult a = exact.Run(x0, seq, 64, 10, {p});
  const RolloutResult b = cvode.Run(x0, seq, 64, 10, {p});
  EXPECT_LT(a.integrated_steps, b.integrated_steps / 4);  // most steps in closed form
  for (int k = 0; k < 64; ++k) EXPECT_NEAR(a.total[k], b.total[k], 1e-6) << "candidate " << k;
}

}  // namespace
}  // namespace ftc
