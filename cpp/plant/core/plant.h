// The plant as a discrete-time system: episodes, termination, interval
// truncation, degradation by operating age, and sensor noise. No LCM inside:
// main.cpp wires it to the bus, bindings.cpp to Python.
#pragma once

#include <cstdint>
#include <memory>
#include <random>

#include "plant/core/degradation.h"
#include "plant/core/integrator.h"
#include "plant/core/linear_step.h"

namespace ftc {

// How a step is integrated. kCvode: CVODE with root finding (the plant process's
// and the reference). kClosedForm: a step with fewer than two valves open in
// closed form (IdleConduitStep, exact), the conduit's affine modes in closed
// form (linear_step.h, exact where CVODE is within its tolerances), CVODE for
// the rest of a step from where the closed form stops (a pinned tank upstream
// of a pump that cannot cover its engine): results differ from kCvode at the
// level of CVODE's tolerances (docs/benchmarks.md quotes the measured error).
enum class StepMethod { kCvode, kClosedForm };

struct StepOutcome {
  Vec6 level = Vec6::Zero();       // true levels after the step, m
  Vec6 observed = Vec6::Zero();    // published levels (true + sensor noise), m
  Valves valves = Valves::Zero();  // valves applied (the command with stuck valves replaced)
  Vec2 deficit = Vec2::Zero();     // unmet engine demand over the step, m^3 (NaN where
                                   // a kClosedForm step ran the conduit's closed form)
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
        const PlantParams& nominal = PlantParams{}, const IntegratorOptions& options = {},
        StepMethod method = StepMethod::kCvode);
  ~Plant();
  Plant(Plant&&) noexcept;
  Plant& operator=(Plant&&) noexcept;
  Plant(const Plant&) = delete;
  Plant& operator=(const Plant&) = delete;

  // Ends the current episode and starts a new operating episode at the current age.
  void Reset();
  // Starts an evaluation episode: parameters and stuck valves frozen at those
  // of the last operating step (the first step's before any), steps not counted.
  void ResetEvaluation();
  // Advances one control step (dt = 1 s) under DegradedParamsAtStep, with the
  // valves stuck at that step overriding u. If the current episode has ended
  // (terminal or truncated), first starts a new one of the same kind.
  const StepOutcome& Step(const Valves& u);

  // The state after the last Reset or Step.
  const StepOutcome& last() const { return last_; }
  bool episode_over() const { return last_.terminal || last_.truncated; }
  std::int64_t operating_steps() const { return operating_steps_; }
  // Sets the operating steps already done (to resume a run at its age); the
  // next step is taken at AgeAt(scenario, steps).
  void SetOperatingSteps(std::int64_t steps) { operating_steps_ = steps; }
  // The operating step whose parameters and stuck valves the next step is
  // taken with: operating_steps() when operating; in an evaluation episode the
  // last operating step's, operating_steps() - 1 (0 before any) when it began.
  std::int64_t step_in_force() const {
    return last_.evaluation ? eval_step_ : operating_steps_;
  }
  // Age the next step would be taken at.
  double current_age() const { return AgeAt(scenario_, step_in_force()); }
  // The scenario's factors at an age, without its events.
  PlantParams ParamsAt(double age) const { return DegradedParams(nominal_, scenario_, age); }
  // Parameters in force during the step after `steps` operating steps (events applied).
  PlantParams ParamsAtStep(std::int64_t steps) const {
    return DegradedParamsAtStep(nominal_, scenario_, steps);
  }
  const FaultScenario& scenario() const { return scenario_; }
  const PlantParams& nominal() const { return nominal_; }
  StepMethod method() const { return method_; }

  // Terminal test: total volume < total engine demand over one step + 1e-6 m^3.
  static bool IsTerminal(const Vec6& x, const PlantParams& p, double dt = 1.0);

 private:
  void StartEpisode(bool evaluation);
  Vec6 Observe(const Vec6& x);
  StepResult Integrate(const Vec6& x, const Valves& u, const PlantParams& p);
  StepIntegrator& Cvode();
  // ParamsAtStep(at), kept from the last call with the same age and events.
  const PlantParams& ParamsInForce(std::int64_t at);

  FaultScenario scenario_;
  PlantParams nominal_;
  IntegratorOptions options_;
  StepMethod method_;
  std::unique_ptr<StepIntegrator> integrator_;  // made on first use (a pool holds thousands)
  std::unique_ptr<LinearStepper> linear_;       // kClosedForm only
  std::mt19937_64 rng_;
  StepOutcome last_;
  std::int64_t operating_steps_ = 0;
  std::int64_t episodes_started_ = 0;
  std::int64_t eval_step_ = 0;  // step_in_force() of the evaluation episode
  PlantParams params_;          // ParamsInForce's, for params_age_ and params_events_
  double params_age_ = 0;
  int params_events_ = 0;
  bool params_valid_ = false;
};

}  // namespace ftc
