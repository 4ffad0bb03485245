// Vector field of plant-model.md on hand-worked cases: flows at one state,
// and the mode decisions (ties, members leaving, pinned empty tanks).
#include <gtest/gtest.h>

#include <cmath>

#include "plant/core/dynamics.h"

namespace ftc {
namespace {

// The field is a handful of additions and divisions; 1e-12 leaves room for
// rounding only.
constexpr double kExact = 1e-12;

Valves MakeValves(std::initializer_list<int> v) {
  Valves u;
  int k = 0;
  for (int e : v) u[k++] = e;
  return u;
}

Vec6 MakeLevels(std::initializer_list<double> v) {
  Vec6 x;
  int k = 0;
  for (double e : v) x[k++] = e;
  return x;
}

TEST(Dynamics, NothingFlowsWhenOpenTanksAreLevel) {
  const PlantParams p;
  const Vec6 x = MakeLevels({0.7, 0.4, 0.7, 0.9, 0.7, 0.7});
  const Valves u = MakeValves({1, 0, 0, 0, 1, 1});  // open tanks all at 0.7
  const Mode mode = ComputeMode(x, u, p);
  const Flows f = ComputeFlows(x, u, p, mode);
  EXPECT_NEAR(f.conduit.cwiseAbs().maxCoeff(), 0.0, kExact);
  // Pumps are untouched: tank 3 feeds E1, tank 4 feeds E2 (0.05 each).
  EXPECT_NEAR(f.supply[2], 0.05, kExact);
  EXPECT_NEAR(f.supply[3], 0.05, kExact);
  EXPECT_NEAR(f.supply.sum(), 0.10, kExact);
}

TEST(Dynamics, SinkInflowAndSourceSplitMatchHandWorkedCase) {
  // Open: tank 1 and tank 5 at 0.8 (tied sources), tank 2 at 0.5, tank 6 at 0.3.
  // Tanks 3, 4 are closed and full, so they meet both demands (0.05 each) and
  // no open tank pumps. With g = 10, R = 100:
  //   V = 10 * 0.8 = 8
  //   q_in(2) = (8 - 5) / 100 = 0.03,  q_in(6) = (8 - 3) / 100 = 0.05,  Q = 0.08
  //   group {1, 5}: rho = (0.08 + 0) / (1 + 1) = 0.04, each supplies 0.04
  //   (equal resistances: the conductance split Q * (1/100) / (2/100) = 0.04 agrees).
  const PlantParams p;
  const Vec6 x = MakeLevels({0.8, 0.5, 1.0, 1.0, 0.8, 0.3});
  const Valves u = MakeValves({1, 1, 0, 0, 1, 1});
  const Mode mode = ComputeMode(x, u, p);
  EXPECT_TRUE(mode.source[0] && mode.source[4]);
  EXPECT_TRUE(mode.sink[1] && mode.sink[5]);
  const Flows f = ComputeFlows(x, u, p, mode);
  EXPECT_NEAR(f.conduit[1], 0.03, kExact);
  EXPECT_NEAR(f.conduit[5], 0.05, kExact);
  EXPECT_NEAR(f.conduit[0], -0.04, kExact);
  EXPECT_NEAR(f.conduit[4], -0.04, kExact);
  EXPECT_NEAR(f.conduit.sum(), 0.0, kExact);
  const Vec6 dx = Derivative(x, u, p, mode);
  EXPECT_NEAR(dx[0], -0.04, kExact);
  EXPECT_NEAR(dx[1], 0.03, kExact);
  EXPECT_NEAR(dx[2], -0.05, kExact);
  EXPECT_NEAR(dx[3], -0.05, kExact);
  EXPECT_NEAR(dx[5], 0.05, kExact);
}

TEST(Dynamics, TiedGroupWithOnePumpFallsTogether) {
  // Tanks 3 and 2 open at 0.8, tank 1 open and empty. Tank 3 pumps E1's 0.05.
  //   q_in(1) = 10 * 0.8 / 100 = 0.08 (tank 1's pump has no demand left: it fills)
  //   rho = (0.08 + 0.05) / 2 = 0.065 >= 0.05 = s_3 / c_3, so tank 3 stays:
  //   tank 3 supplies 0.065 - 0.05 = 0.015, tank 2 supplies 0.065.
  const PlantParams p;
  const Vec6 x = MakeLevels({0.0, 0.8, 0.8, 1.0, 1.0, 1.0});
  const Valves u = MakeValves({1, 1, 1, 0, 0, 0});
  const Mode mode = ComputeMode(x, u, p);
  EXPECT_TRUE(mode.source[1] && mode.source[2]);
  EXPECT_TRUE(mode.sink[0]);
  EXPECT_FALSE(mode.pinned[0]);
  const Flows f = ComputeFlows(x, u, p, mode);
  EXPECT_NEAR(f.conduit[2], -0.015, kExact);
  EXPECT_NEAR(f.conduit[1], -0.065, kExact);
  EXPECT_NEAR(f.conduit[0], 0.08, kExact);
  const Vec6 dx = Derivative(x, u, p, mode);
  EXPECT_EQ(dx[1], dx[2]);  // exactly: tied members must stay tied
  EXPECT_NEAR(dx[2], -0.065, kExact);
  EXPECT_NEAR(dx[0], 0.08, kExact);
}

TEST(Dynamics, MemberWhosePumpOutrunsTheGroupLeavesIt) {
  // Tanks 3 and 2 open at 0.8, nothing else open: rho = 0.05 / 2 = 0.025 < 0.05,
  // so tank 3 leaves and becomes a sink (inflow 0 at first); tank 2 is the source.
  const PlantParams p;
  const Vec6 x = MakeLevels({1.0, 0.8, 0.8, 1.0, 1.0, 1.0});
  const Valves u = MakeValves({0, 1, 1, 0, 0, 0});
  const Mode mode = ComputeMode(x, u, p);
  EXPECT_TRUE(mode.source[1]);
  EXPECT_TRUE(mode.sink[2]);
  const Vec6 dx = Derivative(x, u, p, mode);
  EXPECT_NEAR(dx[2], -0.05, kExact);
  EXPECT_NEAR(dx[1], 0.0, kExact);
}

TEST(Dynamics, AMemberThatLeftATieRejoinsWhenItsPumpNoLongerOutrunsTheGroup) {
  // Tanks 2 and 3 tied at 0.8, tank 1 a sink at x1: q1 = 0.1 (0.8 - x1). Tank 3
  // pumps 0.05 and tank 2 nothing, so with tank 3 in the group rho = (q1 + 0.05) / 2
  // and tank 3 leaves while 0.05 > rho, i.e. q1 < 0.05, x1 > 0.3. Its root is that
  // condition, 0.05 - rho (less half the leave margin): 5e-4 at x1 = 0.31, whether
  // tank 3 sits one ulp above, at or one ulp below tank 2 (the tie's rounding
  // cannot put it on the wrong side, as it could the gap x2 - x3), and -5e-4 once
  // tank 1 is at 0.29, where ComputeMode takes tank 3 back into the group.
  const PlantParams p;
  const Valves u = MakeValves({1, 1, 1, 0, 0, 0});
  const double margin = 0.5 * 1e-12 * 0.05;  // dynamics.cpp: half of kLeaveMargin * s
  for (const double x3 : {std::nextafter(0.8, 1.0), 0.8, std::nextafter(0.8, 0.0)}) {
    const Vec6 x = MakeLevels({0.31, 0.8, x3, 1.0, 1.0, 1.0});
    const Mode mode = ComputeMode(x, u, p);
    ASSERT_TRUE(mode.sink[2] && mode.left[2]);
    ASSERT_TRUE(mode.source[1] && !mode.left[0]);
    EXPECT_NEAR(RootFunctions(x, u, p, mode)[kTanks + 2], 5e-4 - margin, 1e-15);
    Vec6 later = x;
    later[0] = 0.29;
    EXPECT_NEAR(RootFunctions(later, u, p, mode)[kTanks + 2], -5e-4 - margin, 1e-15);
    const Mode rejoined = ComputeMode(later, u, p);
    EXPECT_TRUE(rejoined.source[1] && rejoined.source[2] && !rejoined.left[2]);
  }
}

TEST(Dynamics, AMemberThatDrawsNothingStaysWhenTheTieIsBrokenByOneUlp) {
  // As above, but tank 3 one ulp above tank 2 (where a located root can leave
  // them): tank 3 leaves, and the sink it becomes sits above the group, so its
  // inflow and the group's rate are a rounding error below 0; tank 2, whose
  // pump draws nothing (engine 1 is fed by tank 3), must not leave too, or no
  // source is left and the sinks drain into an empty conduit (fuel lost).
  const PlantParams p;
  const double level = 0.5394131063666735;
  const Vec6 x = MakeLevels({1.0, level, std::nextafter(level, 1.0), 1.0, 1.0, 1.0});
  const Valves u = MakeValves({0, 1, 1, 0, 0, 0});
  const Mode mode = ComputeMode(x, u, p);
  EXPECT_TRUE(mode.source[1]);
  EXPECT_TRUE(mode.sink[2]);
  Vec6 dx;
  Flows flows;
  EvaluateField(x, p, mode, &dx, &flows);
  EXPECT_NEAR(flows.conduit.sum(), 0.0, kExact);  // the conduit moves fuel, never loses it
  EXPECT_NEAR(dx[2], -0.05, kExact);
  EXPECT_NEAR(dx[1], 0.0, kExact);
}

TEST(Dynamics, EmptyTankWithSmallInflowIsPinnedAndPassesItOn) {
  // Tank 3 open and empty, tank 1 open at 0.3: q_in(3) = 10 * 0.3 / 100 = 0.03 <
  // min(p, d) = 0.05, so tank 3 stays at 0 and supplies 0.03; tank 2 (closed)
  // supplies the remaining 0.02; tank 1 has no demand left.
  const PlantParams p;
  const Vec6 x = MakeLevels({0.3, 0.5, 0.0, 1.0, 1.0, 1.0});
  const Valves u = MakeValves({1, 0, 1, 0, 0, 0});
  const Mode mode = ComputeMode(x, u, p);
  EXPECT_TRUE(mode.pinned[2]);
  const Flows f = ComputeFlows(x, u, p, mode);
  EXPECT_NEAR(f.supply[2], 0.03, kExact);
  EXPECT_NEAR(f.supply[1], 0.02, kExact);
  EXPECT_NEAR(f.supply[0], 0.0, kExact);
  EXPECT_NEAR(f.deficit[0], 0.0, kExact);
  const Vec6 dx = Derivative(x, u, p, mode);
  EXPECT_EQ(dx[2], 0.0);
  EXPECT_NEAR(dx[0], -0.03, kExact);
}

TEST(Dynamics, DeficitWhenTheWingIsEmpty) {
  const PlantParams p;
  const Vec6 x = MakeLevels({0.0, 0.0, 0.0, 0.0, 0.0, 0.02});
  const Valves u = Valves::Zero();
  const Flows f = ComputeFlows(x, u, p, ComputeMode(x, u, p));
  EXPECT_NEAR(f.deficit[0], 0.05, kExact);
  EXPECT_NEAR(f.deficit[1], 0.0, kExact);
  EXPECT_NEAR(f.supply[5], 0.05, kExact);
}

TEST(Dynamics, RootFunctionsArePositiveInsideTheirMode) {
  const PlantParams p;
  const Vec6 x = MakeLevels({0.3, 0.5, 0.0, 0.6, 0.9, 0.2});
  const Valves u = MakeValves({1, 0, 0, 1, 1, 1});
  const auto r = RootFunctions(x, u, p, ComputeMode(x, u, p));
  for (int k = 0; k < kNumRoots; ++k) EXPECT_GT(r[k], 0.0) << "root " << k;
}

TEST(Dynamics, ALevelBelowZeroEndsTheModeOfASinkOnlyOnceItIsNoLongerFilled) {
  // Engine 1 (demand 0.1) fed by empty tanks 3 and 2 through the conduit from
  // tank 1 (pump dead): tank 3 is pinned, passing q = 0.1 x1, and tank 2 may
  // draw the rest, 0.1 - q. With x1 = 0.5 + 1e-6, tank 2's inflow q exceeds
  // that by 2e-7 m^3/s: it rises off the bottom, towards the level x_eq =
  // x1 - (0.1 - q) R / g = 2e-6 m at which its inflow would equal its draw.
  PlantParams p;
  p.pump[0] = 0.0;
  p.demand[0] = 0.1;
  const Valves u = MakeValves({1, 1, 1, 0, 0, 0});
  Vec6 x = MakeLevels({0.5 + 1e-6, 0.0, 0.0, 0.5, 0.5, 0.5});
  const Mode mode = ComputeMode(x, u, p);
  ASSERT_TRUE(mode.pinned[2]);
  ASSERT_TRUE(mode.pumping[1] && mode.sink[1] && !mode.pinned[1]);
  // At or above 0 the level root is the level (plus a 1e-15 offset) ...
  const double at_zero = RootFunctions(x, u, p, mode)[1];
  EXPECT_GT(at_zero, 0.0);
  EXPECT_LT(at_zero, 1e-14);
  x[1] = 0.25;
  EXPECT_NEAR(RootFunctions(x, u, p, mode)[1], 0.25, 1e-14);
  // ... but an integrated level 1e-12 below 0 while the tank is filled (inside
  // any tolerance we integrate at) does not end the mode: min(x_eq, 1e-12).
  x[1] = -1e-12;
  const double filled = RootFunctions(x, u, p, mode)[1];
  EXPECT_GT(filled, 0.9e-12);
  EXPECT_LT(filled, 1.1e-12);
  // Once the inflow has fallen below the draw (x_eq < 0) it does, and at
  // x_2 = 0 ComputeMode pins the tank: the located root changes the mode.
  x[0] = 0.5 - 1e-6;
  EXPECT_LT(RootFunctions(x, u, p, mode)[1], 0.0);
  x[1] = 0.0;
  EXPECT_TRUE(ComputeMode(x, u, p).pinned[1]);
  // A draining sink's level below 0 is its bottom, as before.
  x = MakeLevels({0.4, -1e-12, 0.0, 0.5, 0.5, 0.5});  // inflow 0.04 < draw 0.06
  EXPECT_NEAR(RootFunctions(x, u, p, mode)[1], -1e-12 + 1e-15, 1e-20);
}

}  // namespace
}  // namespace ftc
