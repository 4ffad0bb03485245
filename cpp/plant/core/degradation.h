// Fault scenarios and the degraded parameters at a given age
// (plant-model.md, "Degradation").
#pragma once

#include <cstdint>
#include <limits>
#include <string>

#include "plant/core/params.h"

namespace ftc {

enum class DegradationMode { kStepwise, kContinuous };

struct FaultScenario {
  std::string name = "nominal";
  Vec6 tank_factor = Vec6::Constant(std::numeric_limits<double>::infinity());  // D_T,i
  Vec2 engine_factor = Vec2::Constant(std::numeric_limits<double>::infinity()); // D_E,j
  DegradationMode mode = DegradationMode::kStepwise;
  double noise_std = 0.0;       // sensor noise on published levels, m
  bool random_start = false;    // start levels uniform in [0.8 h, h] instead of full
  int steps_per_interval = 512; // control steps per degradation interval (t_online)
};

// p_i(a) = p_i0 max(0, 1 - a/D_T,i); R_i(a) = R_i0 (1 + a/D_T,i); d_j(a) = d_j0 (1 + a/D_E,j).
PlantParams DegradedParams(const PlantParams& nominal, const FaultScenario& s, double age);

// Age (intervals) in force during a step that starts after `operating_steps`
// counted steps: floor(steps / steps_per_interval) stepwise, the ratio continuous.
double AgeAt(const FaultScenario& s, std::int64_t operating_steps);

}  // namespace ftc
