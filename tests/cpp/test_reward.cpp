// Reward of plant-model.md on hand-computed states.
#include <gtest/gtest.h>

#include <cmath>

#include "plant/core/reward.h"

namespace ftc {
namespace {

constexpr double kExact = 1e-12;  // a few sums and a square root

TEST(Reward, FullBalancedPlant) {
  // cg = 0; sigma^2 = (9 + 4 + 1 + 1 + 4 + 9) / 6 = 14/3.
  const RewardTerms t = ComputeReward(Vec6::Ones(), Valves::Zero(), PlantParams{});
  EXPECT_NEAR(t.cg, 0.0, kExact);
  EXPECT_NEAR(t.spread, std::sqrt(14.0 / 3.0), kExact);
  EXPECT_NEAR(t.reward, std::sqrt(14.0 / 3.0), kExact);
}

TEST(Reward, UnbalancedPlantWithOpenValves) {
  // Only tanks 5 (arm 2) and 6 (arm 3) hold fuel, 0.5 m each:
  //   cg = (0.5*2 + 0.5*3) / 1 = 2.5, sigma = 0.5, u_bar = 2/6,
  //   r = (1 - 2.5/3) * 0.5 - 1/3 = 1/12 - 1/3 = -0.25.
  Vec6 x = Vec6::Zero();
  x[4] = x[5] = 0.5;
  x[0] = -0.01;  // negative (noisy) levels count as empty
  Valves u = Valves::Zero();
  u[0] = u[1] = 1;
  const RewardTerms t = ComputeReward(x, u, PlantParams{});
  EXPECT_NEAR(t.cg, 2.5, kExact);
  EXPECT_NEAR(t.spread, 0.5, kExact);
  EXPECT_NEAR(t.activity, 1.0 / 3.0, kExact);
  EXPECT_NEAR(t.reward, -0.25, kExact);
}

TEST(Reward, EmptyPlantHasNoCentreOfGravity) {
  Vec6 x = Vec6::Constant(1e-8);  // W = 6e-8 < 1e-6
  const RewardTerms t = ComputeReward(x, Valves::Ones(), PlantParams{});
  EXPECT_EQ(t.cg, 0.0);
  EXPECT_EQ(t.spread, 0.0);
  EXPECT_NEAR(t.reward, -1.0, kExact);
}

}  // namespace
}  // namespace ftc
