// Reward of plant-model.md, "Reward"; mirrors python/ftc/plant/reward.py.
#include "plant/core/reward.h"

#include <algorithm>
#include <cmath>

namespace ftc {

// Below this total volume (m^3) the plant is empty up to integration error.
constexpr double kEmptyVolume = 1e-6;

RewardTerms ComputeReward(const Vec6& x_next, const Valves& u, const PlantParams& p) {
  const Vec6 arms = MomentArms();
  const Vec6 w = p.area.cwiseProduct(x_next.cwiseMax(0.0));
  const double total = w.sum();
  RewardTerms t;
  t.activity = static_cast<double>((u.array() != 0).count()) / kTanks;
  if (total >= kEmptyVolume) {
    t.cg = w.dot(arms) / total;
    const double var = w.dot((arms.array() - t.cg).square().matrix()) / total;
    t.spread = std::sqrt(std::max(var, 0.0));
  }
  t.reward = (1.0 - std::abs(t.cg) / arms.cwiseAbs().maxCoeff()) * t.spread - t.activity;
  return t;
}

}  // namespace ftc
