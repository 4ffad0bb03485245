// Reward of plant-model.md, "Reward", for the C++ batch rollouts. The Python
// definition (python/ftc/plant/reward.py) is the reference;
// tests/python/test_physics_vs_reference.py checks that both agree.
#pragma once

#include "plant/core/params.h"

namespace ftc {

struct RewardTerms {
  double reward = 0;    // (1 - |cg|/max|m|) * sigma - u_bar
  double cg = 0;        // centre of gravity, arm units
  double spread = 0;    // sigma, arm units
  double activity = 0;  // fraction of open valves
};

RewardTerms ComputeReward(const Vec6& x_next, const Valves& u, const PlantParams& p);

}  // namespace ftc
