// The plant as a discrete-time system: episodes, termination, interval
// truncation, degradation by operating age, and sensor noise. No LCM inside:
// main.cpp wires it to the bus, bindings.cpp to Python.
#pragma once

#include <cstdint>
#include <random>

#include "plant/core/degradation.h"
#include "plant/core/integrator.h"

namespace ftc {

struct StepOutcome {
  Vec6 level = Vec6::Zero();       // true levels after the step, m
  Vec6 observed = Vec6::Zero();    // published levels (true + sensor noise), m
  Valves valves = Valves::Zero();  // valves applied
  Vec2 deficit = Vec2::Zero();     // unmet engine demand over the step, m^3
  double age = 0;                  // age in force during the step, intervals
  int step = 0;                    // steps taken in this episode (1 after the first)
  std::int64_t episode = 0;
  bool terminal = false;           // fuel <= one step of total demand (+1e-6 m^3)
  bool truncated = false;          // interval boundary reached (and not terminal)
  bool evaluation = false;
};

class Plant final {
 public:
  Plant(const FaultScenario& scenario, std::uint64_t seed,
        const PlantParams& nominal = PlantParams{}, const IntegratorOptions& options = {});

  // Ends the current episode and starts a new operating episode at the current age.
  void Reset();
  // Starts an evaluation episode: age frozen at the age of the last operating
  // step (0 before any), steps not counted towards the age.
  void ResetEvaluation();
  // Advances one control step (dt = 1 s). If the current episode has ended
  // (terminal or truncated), first starts a new one of the same kind.
  const StepOutcome& Step(const Valves& u);

  // The state after the last Reset or Step.
  const StepOutcome& last() const { return last_; }
  bool episode_over() const { return last_.terminal || last_.truncated; }
  std::int64_t operating_steps() const { return operating_steps_; }
  // Sets the operating steps already done (to resume a run at its age); the
  // next step is taken at AgeAt(scenario, steps).
  void SetOperatingSteps(std::int64_t steps) {
    operating_steps_ = steps;
    last_operating_age_ = steps > 0 ? AgeAt(scenario_, steps - 1) : 0.0;
  }
  // Age the next step would be taken at.
  double current_age() const;
  PlantParams ParamsAt(double age) const { return DegradedParams(nominal_, scenario_, age); }
  const FaultScenario& scenario() const { return scenario_; }
  const PlantParams& nominal() const { return nominal_; }

  // Terminal test: total volume < total engine demand over one step + 1e-6 m^3.
  static bool IsTerminal(const Vec6& x, const PlantParams& p, double dt = 1.0);

 private:
  void StartEpisode(bool evaluation);
  Vec6 Observe(const Vec6& x);

  FaultScenario scenario_;
  PlantParams nominal_;
  StepIntegrator integrator_;
  std::mt19937_64 rng_;
  StepOutcome last_;
  std::int64_t operating_steps_ = 0;
  std::int64_t episodes_started_ = 0;
  double eval_age_ = 0;
  double last_operating_age_ = 0;
};

}  // namespace ftc
