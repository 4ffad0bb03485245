// Fault scenario files (TOML). Keys:
//   name = "single"                 optional, string
//   tank_factor = [inf, ..., 20.0]  six D_T values, >= 1e-3, inf = healthy (default all inf)
//   engine_factor = [20.0, inf]     two D_E values, >= 1e-3, inf = healthy (default all inf)
//   degradation = "stepwise"        or "continuous"
//   steps_per_interval = 512        > 0
//   [noise] std = 0.0               >= 0, metres
//   [start] random = false          levels uniform in [0.8 h, h] when true
//   [[event]]                       abrupt faults, any number, in any order:
//     at_step = 2600                from this operating step on (integer >= 0, 0-based
//                                   count of operating steps taken; evaluation steps
//                                   do not count)
//     and exactly one of
//     tank = 4, factor = 2.0        tank 4 (1-based; its pump and valve) gets D_T = factor
//     engine = 1, factor = 3.0      engine 1 (1-based) gets D_E = factor
//     stuck_valve = 2, state = "open"  valve 2 (1-based) stays "open" or "closed"
//   A factor (>= 1e-3, inf = healthy) replaces the component's D at the same
//   age: the parameter jumps. Of two events on one component at one step the
//   later in the file wins.
// Any other key, a wrong length or type, or a non-positive or NaN factor is a
// ScenarioError naming the file and key (events: 'event[n].<key>', n 1-based).
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
