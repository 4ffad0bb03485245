// Degradation formulas of plant-model.md at a few ages, stepwise and continuous.
#include <gtest/gtest.h>

#include <limits>

#include "plant/core/degradation.h"

namespace ftc {
namespace {

// Closed-form products of a few doubles: rounding only.
constexpr double kExact = 1e-12;

TEST(Degradation, SpecExampleInIntervalNine) {
  // plant-model.md: with D = 20, in interval 9 a pump gives 55% of nominal,
  // a valve has 145% of its resistance, an engine burns 145% of its demand.
  FaultScenario s;
  s.tank_factor[4] = 20.0;
  s.engine_factor[0] = 20.0;
  const PlantParams n;
  const PlantParams p = DegradedParams(n, s, AgeAt(s, 9 * 512 + 100));
  EXPECT_NEAR(p.pump[4], 0.55 * n.pump[4], kExact);
  EXPECT_NEAR(p.resistance[4], 1.45 * n.resistance[4], kExact);
  EXPECT_NEAR(p.demand[0], 1.45 * n.demand[0], kExact);
  // Healthy components (D = inf) keep their nominal values at any age.
  EXPECT_EQ(p.pump[0], n.pump[0]);
  EXPECT_EQ(p.resistance[3], n.resistance[3]);
  EXPECT_EQ(p.demand[1], n.demand[1]);
}

TEST(Degradation, PumpCapacityBottomsOutAtZero) {
  FaultScenario s;
  s.tank_factor[0] = 10.0;
  const PlantParams p = DegradedParams(PlantParams{}, s, 15.0);
  EXPECT_EQ(p.pump[0], 0.0);
  EXPECT_NEAR(p.resistance[0], 100.0 * 2.5, kExact);
}

TEST(Degradation, AgeIsStepwiseByDefaultAndContinuousOnRequest) {
  FaultScenario s;
  EXPECT_EQ(AgeAt(s, 0), 0.0);
  EXPECT_EQ(AgeAt(s, 511), 0.0);
  EXPECT_EQ(AgeAt(s, 512), 1.0);
  EXPECT_EQ(AgeAt(s, 5 * 512 + 300), 5.0);
  s.mode = DegradationMode::kContinuous;
  EXPECT_NEAR(AgeAt(s, 256), 0.5, kExact);
  EXPECT_NEAR(AgeAt(s, 5 * 512 + 384), 5.75, kExact);
  s.engine_factor[1] = 25.0;
  const PlantParams p = DegradedParams(PlantParams{}, s, AgeAt(s, 5 * 512 + 384));
  EXPECT_NEAR(p.demand[1], 0.05 * (1 + 5.75 / 25.0), kExact);
  s.steps_per_interval = 100;
  s.mode = DegradationMode::kStepwise;
  EXPECT_EQ(AgeAt(s, 250), 2.0);
}

}  // namespace
}  // namespace ftc
