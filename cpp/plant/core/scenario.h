// Fault scenario files (TOML). Keys:
//   name = "single"                 optional, string
//   tank_factor = [inf, ..., 20.0]  six D_T values, >= 1e-3, inf = healthy (default all inf)
//   engine_factor = [20.0, inf]     two D_E values, >= 1e-3, inf = healthy (default all inf)
//   degradation = "stepwise"        or "continuous"
//   steps_per_interval = 512        > 0
//   [noise] std = 0.0               >= 0, metres
//   [start] random = false          levels uniform in [0.8 h, h] when true
// Any other key, a wrong length or type, or a non-positive or NaN factor is a
// ScenarioError naming the file and key.
#pragma once

#include <stdexcept>
#include <string>

#include "plant/core/degradation.h"

namespace ftc {

class ScenarioError final : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

FaultScenario LoadScenario(const std::string& path);
FaultScenario ParseScenario(const std::string& toml_text, const std::string& source_name);

}  // namespace ftc
