// Closed-form steps with the conduit active, for batch rollouts (rollout.h).
//
// Within a mode the field is affine in the levels (dynamics.cpp), and its
// conduit part is a star of conductances g / R_k between the source group
// (its tanks tied, falling together) and each sink: x' = M x + b with
// M = C^-1 L, L symmetric and C the nodes' areas (a pinned tank, held
// at 0, is a conductance from the group to the ground). So the levels follow
// exponentials, x(t) = x0 + V diag((e^{lambda t} - 1) / lambda) V^-1 f(x0),
// from one symmetric eigendecomposition of C^1/2 M C^-1/2, and the root
// functions (affine in x) are sums of those exponentials: their first
// downward crossing is bracketed on a grid and located by Newton's method kept
// inside the bracket, to rounding, where CVODE locates it within its tolerances. Where a pinned
// tank's inflow drives a tank off the conduit, M is not of that kind and a
// general real eigendecomposition stands in. M and b are read off the field
// itself (dynamics.cpp stays the one statement of the physics), at the levels
// 0, so a mode's preparation depends on the mode, the valves, the root slots
// in force and the parameters alone: each thread keeps the last 4,096 it made
// (~9 MB), shared by every plant it steps, so a pool of plants with the same
// parameters prepares each mode it meets once (random valves meet ~1,200).
#pragma once

#include <memory>

#include "plant/core/integrator.h"

namespace ftc {

struct LinearStepResult {
  Vec6 x = Vec6::Zero();  // levels where the closed form stopped, m
  double t = 0;           // time reached, s (dt unless a mode it does not handle began)
  int events = 0;         // mode switches located
};

// Steps in closed form, taking modes' preparations (their eigenvectors and the
// roots' gradients, which do not depend on the levels) from the calling
// thread's cache.
class LinearStepper final {
 public:
  LinearStepper();
  ~LinearStepper();
  LinearStepper(const LinearStepper&) = delete;
  LinearStepper& operator=(const LinearStepper&) = delete;

  // See LinearConduitStep.
  LinearStepResult Step(const Vec6& x0, const Valves& u, const PlantParams& p, double dt,
                        int max_events = 1000);

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// Integrates dt seconds from x0 with valves u in closed form, mode by mode,
// as StepIntegrator::Step would (a located level root makes the tank exactly
// empty; levels within 1e-12 m of 0 snap to 0 at segment boundaries). Stops
// early, at .t < dt, where a mode begins that is not affine in that way (a
// pinned tank passes its inflow on, and a pump after it in the engine's order
// draws min(p, remaining), which has a kink where p < demand); the caller
// integrates the rest. Throws std::runtime_error after max_events switches.
// (A fresh LinearStepper's Step.)
LinearStepResult LinearConduitStep(const Vec6& x0, const Valves& u, const PlantParams& p,
                                   double dt, int max_events = 1000);

}  // namespace ftc
