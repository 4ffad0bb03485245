// Linear degradation by operating age (plant-model.md, "Degradation").
#include "plant/core/degradation.h"

#include <algorithm>

namespace ftc {

PlantParams DegradedParams(const PlantParams& nominal, const FaultScenario& s, double age) {
  PlantParams p = nominal;
  for (int i = 0; i < kTanks; ++i) {
    const double wear = age / s.tank_factor[i];  // 0 for a healthy tank (D = inf)
    p.pump[i] = nominal.pump[i] * std::max(0.0, 1.0 - wear);
    p.resistance[i] = nominal.resistance[i] * (1.0 + wear);
  }
  for (int j = 0; j < kEngines; ++j)
    p.demand[j] = nominal.demand[j] * (1.0 + age / s.engine_factor[j]);
  return p;
}

double AgeAt(const FaultScenario& s, std::int64_t operating_steps) {
  if (s.mode == DegradationMode::kContinuous)
    return static_cast<double>(operating_steps) / s.steps_per_interval;
  return static_cast<double>(operating_steps / s.steps_per_interval);
}

}  // namespace ftc
