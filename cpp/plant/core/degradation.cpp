// Linear degradation by operating age, and abrupt faults by operating step
// (plant-model.md, "Degradation"; the events of FaultScenario).
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

FaultScenario FactorsAtStep(const FaultScenario& s, std::int64_t operating_steps) {
  FaultScenario out = s;
  for (const FaultEvent& e : s.events) {
    if (e.at_step > operating_steps) break;  // sorted by at_step
    if (e.kind == FaultEvent::Kind::kTank) out.tank_factor[e.index] = e.factor;
    if (e.kind == FaultEvent::Kind::kEngine) out.engine_factor[e.index] = e.factor;
  }
  return out;
}

PlantParams DegradedParamsAtStep(const PlantParams& nominal, const FaultScenario& s,
                                 std::int64_t operating_steps) {
  const double age = AgeAt(s, operating_steps);
  if (s.events.empty()) return DegradedParams(nominal, s, age);  // no copy on the hot path
  return DegradedParams(nominal, FactorsAtStep(s, operating_steps), age);
}

StuckValves StuckValvesAtStep(const FaultScenario& s, std::int64_t operating_steps) {
  StuckValves stuck;
  for (const FaultEvent& e : s.events) {
    if (e.at_step > operating_steps) break;
    if (e.kind != FaultEvent::Kind::kStuckValve) continue;
    stuck.mask[e.index] = 1;
    stuck.state[e.index] = e.state;
  }
  return stuck;
}

}  // namespace ftc
