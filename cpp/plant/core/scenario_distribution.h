// A declared distribution of fault scenarios, drawn from a seed: what a batch
// of plants (pool.h) sweeps. Every scenario it draws is a FaultScenario that
// the plant process could read from a file (scenario.h).
//
// Draw of one scenario, in this order from one std::mt19937_64:
//   * each tank is worn (linear degradation) with tank_probability, its D_T
//     uniform in tank_factor; each engine likewise (engine_*);
//   * with dead_pump_probability, one tank (uniform) loses its pump at an
//     operating step uniform in [steps_per_interval, life_intervals *
//     steps_per_interval): an abrupt tank event with factor kDeadFactor, which
//     at any age >= 1 interval leaves p_i = 0 (and the valve's resistance
//     x(1 + 1000 a)): the only way the model has to kill a pump;
//   * with event_probability, one component (a tank or an engine, 8 equally
//     likely) jumps to a factor uniform in event_factor at an operating step
//     uniform in [0, life_intervals * steps_per_interval);
//   * with stuck_valve_probability, one valve (uniform) sticks, open or closed
//     with probability 1/2 each, at a step drawn as for the event;
//   * with noise_probability, sensor noise of std uniform in noise_std.
#pragma once

#include <cstdint>
#include <random>
#include <string>
#include <utility>
#include <vector>

#include "plant/core/degradation.h"

namespace ftc {

// Factor of an abrupt "dead pump" event: the scenario files' smallest (>= 1e-3).
constexpr double kDeadFactor = 1e-3;

struct ScenarioDistribution {
  using Range = std::pair<double, double>;  // [low, high]
  DegradationMode mode = DegradationMode::kStepwise;
  int steps_per_interval = 512;
  int life_intervals = 10;  // events are drawn within the first life_intervals intervals
  double tank_probability = 0.25;
  Range tank_factor{6.0, 30.0};
  double engine_probability = 0.5;
  Range engine_factor{6.0, 30.0};
  double dead_pump_probability = 0.0;
  double event_probability = 0.0;
  Range event_factor{2.0, 10.0};
  double stuck_valve_probability = 0.0;
  double noise_probability = 0.0;
  Range noise_std{0.0, 0.01};

  // Throws std::invalid_argument (one line, naming the field) unless every
  // probability is in [0, 1], every range is finite with low <= high, factors
  // are >= 1e-3, noise >= 0, steps_per_interval > 0 and life_intervals >= 1
  // (>= 2 with a dead pump, which dies after the first interval).
  void Validate() const;

  // Throws std::invalid_argument (one line: the key, its value and the declared
  // range) unless the scenario is one this distribution can draw: its mode and
  // interval, its finite factors in their ranges, its events of the declared
  // kinds, its noise in range (or 0).
  void Check(const FaultScenario& s) const;

  // One scenario from rng (see the file comment), named "drawn".
  FaultScenario Draw(std::mt19937_64& rng) const;
};

// `count` scenarios drawn from one seed (Validate()d first).
std::vector<FaultScenario> DrawScenarios(const ScenarioDistribution& d, int count,
                                         std::uint64_t seed);

// SplitMix64: a seed per (base, stream) that shares no state with its neighbours.
std::uint64_t MixSeed(std::uint64_t base, std::uint64_t stream);

}  // namespace ftc
