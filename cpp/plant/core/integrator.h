// RAII wrapper around SUNDIALS CVODE integrating one control step of the
// hybrid tank dynamics with root finding at every mode switch.
#pragma once

#include <memory>

#include "plant/core/dynamics.h"

namespace ftc {

struct IntegratorOptions {
  double rtol = 1e-8;   // relative tolerance (justified in integrator.cpp)
  double atol = 1e-10;  // absolute tolerance, m
  int max_events = 1000;  // per step; exceeded => std::runtime_error (chattering)
};

// Result of integrating one control step.
struct StepResult {
  Vec6 x = Vec6::Zero();               // levels at the end of the step, m
  Vec6 supplied = Vec6::Zero();        // fuel pumped from each tank over the step, m^3
  Vec2 deficit = Vec2::Zero();         // unmet engine demand over the step, m^3
  int events = 0;                      // mode switches located during the step
};

class StepIntegrator final {
 public:
  explicit StepIntegrator(const IntegratorOptions& options = {});
  ~StepIntegrator();
  StepIntegrator(const StepIntegrator&) = delete;
  StepIntegrator& operator=(const StepIntegrator&) = delete;

  // Integrates dx/dt from x0 over dt seconds with valves u held constant.
  // Throws std::runtime_error naming the SUNDIALS function and code on failure.
  StepResult Step(const Vec6& x0, const Valves& u, const PlantParams& p, double dt = 1.0);

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace ftc
