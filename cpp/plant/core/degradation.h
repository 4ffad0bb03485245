// Fault scenarios and the degraded parameters at a given age and operating
// step (plant-model.md, "Degradation"; abrupt faults: issue 11 item 4).
#pragma once

#include <cstdint>
#include <limits>
#include <string>
#include <vector>

#include "plant/core/params.h"

namespace ftc {

enum class DegradationMode { kStepwise, kContinuous };

// An abrupt fault: from operating step `at_step` on (0-based count of operating
// steps taken before the step; evaluation steps do not count), either one
// component's degradation factor D is replaced (the age is unchanged, so the
// parameter jumps), or one valve is stuck in `state` whatever is commanded.
struct FaultEvent {
  enum class Kind { kTank, kEngine, kStuckValve };
  std::int64_t at_step = 0;
  Kind kind = Kind::kTank;
  int index = 0;        // 0-based tank (kTank, kStuckValve) or engine (kEngine)
  double factor = std::numeric_limits<double>::infinity();  // new D (kTank, kEngine)
  int state = 0;        // kStuckValve: 0 closed, 1 open
};

struct FaultScenario {
  std::string name = "nominal";
  Vec6 tank_factor = Vec6::Constant(std::numeric_limits<double>::infinity());  // D_T,i
  Vec2 engine_factor = Vec2::Constant(std::numeric_limits<double>::infinity()); // D_E,j
  DegradationMode mode = DegradationMode::kStepwise;
  double noise_std = 0.0;       // sensor noise on published levels, m
  bool random_start = false;    // start levels uniform in [0.8 h, h] instead of full
  int steps_per_interval = 512; // control steps per degradation interval (t_online)
  // Abrupt faults, sorted by at_step (stable: of two events at one step on one
  // component, the later in the file wins). Empty: the paper's linear faults only.
  std::vector<FaultEvent> events;
};

// p_i(a) = p_i0 max(0, 1 - a/D_T,i); R_i(a) = R_i0 (1 + a/D_T,i); d_j(a) = d_j0 (1 + a/D_E,j).
// The scenario's own factors only: the events are not consulted.
PlantParams DegradedParams(const PlantParams& nominal, const FaultScenario& s, double age);

// Age (intervals) in force during a step that starts after `operating_steps`
// counted steps: floor(steps / steps_per_interval) stepwise, the ratio continuous.
double AgeAt(const FaultScenario& s, std::int64_t operating_steps);

// The scenario with the factor events of at_step <= operating_steps applied to
// its factors (events left as they were).
FaultScenario FactorsAtStep(const FaultScenario& s, std::int64_t operating_steps);

// Parameters in force during the step taken after `operating_steps` counted
// steps: the factors of FactorsAtStep at the age AgeAt(s, operating_steps).
// Without events, exactly DegradedParams(nominal, s, AgeAt(s, operating_steps)).
PlantParams DegradedParamsAtStep(const PlantParams& nominal, const FaultScenario& s,
                                 std::int64_t operating_steps);

// Valves stuck during that step: mask[i] = 1 if valve i is stuck, state[i] its
// position (0 where not stuck).
struct StuckValves {
  Valves mask = Valves::Zero();
  Valves state = Valves::Zero();
  bool any() const { return mask.any(); }
  // The valves the plant applies for a command u: u with the stuck ones replaced.
  Valves Apply(const Valves& u) const {
    return (mask.array() != 0).select(state, u);
  }
};
StuckValves StuckValvesAtStep(const FaultScenario& s, std::int64_t operating_steps);

}  // namespace ftc
