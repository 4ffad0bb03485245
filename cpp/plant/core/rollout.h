// Batch rollouts for planners: many candidate valve sequences simulated from
// one state with the true physics and the plant's episode rule, returning the
// summed rewards. The inner loop of the oracle MPC (python/ftc/mpc.py); no
// LCM and no Python here (bindings.cpp exposes it as _core.batch_rollout).
#pragma once

#include <vector>

#include "plant/core/degradation.h"
#include "plant/core/integrator.h"
#include "plant/core/linear_step.h"

namespace ftc {

struct RolloutOptions {
  // Steps with fewer than two valves open leave the conduit idle; the field
  // is then piecewise constant (pumps only) and integrated in closed form
  // instead of by CVODE (exact; CVODE is within its 1e-8 tolerance of it).
  bool exact_idle_conduit = true;
  // Candidates sharing a prefix of valve settings simulate it once.
  bool share_prefixes = true;
  // Steps with the conduit active in closed form too (linear_step.h: exact
  // where CVODE is within its tolerances, so results move at that level);
  // CVODE integrates what it does not handle (modes with a pinned tank).
  bool exact_active_conduit = false;
};

// The rollouts of one batch, candidate-major: entry (k, t) at k * horizon + t.
struct RolloutResult {
  std::vector<double> total;             // K summed rewards
  std::vector<double> rewards;           // K x L reward of each step
  std::vector<Vec6> levels;              // K x L levels after each step (before any reset), m
  std::vector<unsigned char> terminal;   // K x L: the episode ended at this step (then full tanks)
  long integrated_steps = 0;             // steps integrated by CVODE
  long exact_steps = 0;                  // steps in closed form (idle, or active if asked)
  long shared_steps = 0;                 // steps reused from another candidate's prefix
};

// One step with fewer than two valves open, exactly: the field is constant
// between pump switches (a tank running dry), located in closed form.
// Throws std::invalid_argument if two or more valves are open.
StepResult IdleConduitStep(const Vec6& x0, const Valves& u, const PlantParams& p, double dt);

// The balance rule (python/ftc/control/agents/balance.py is the reference;
// tests/python/test_balance_rule.py checks that both agree): where the
// levels' centre of gravity (arm units, weights p.area * max(level, 0); the
// Python rule takes the nominal areas, which no degradation changes) is
// further than band from the axis, the fullest tank of the heavy wing and the
// emptiest of the light one open (the first of each on ties); otherwise, or
// with no fuel, every valve is closed.
Valves BalanceValves(const Vec6& x, const PlantParams& p, double band);

class BatchRollout final {
 public:
  explicit BatchRollout(const IntegratorOptions& integrator = {},
                        const RolloutOptions& options = {});
  BatchRollout(const BatchRollout&) = delete;
  BatchRollout& operator=(const BatchRollout&) = delete;

  // Simulates each candidate from x0 for `horizon` steps of dt seconds.
  // sequences: num_candidates x horizon valve settings, candidate-major.
  // params: one set for every step, or `horizon` sets (step t under params[t],
  // e.g. degraded at the age in force at that step). As the plant does, a
  // step after which Plant::IsTerminal holds ends the episode and the next
  // step starts from full tanks (params' heights). Rewards: ComputeReward.
  RolloutResult Run(const Vec6& x0, const std::vector<Valves>& sequences, int num_candidates,
                    int horizon, const std::vector<PlantParams>& params, double dt = 1.0);

  // One step of dt seconds from each of many states, row n from x[n] with
  // valves u[n] (no episode rule: the levels after the step). A row the
  // integrator refuses (e.g. chattering under estimated parameters) is NaN
  // in every entry and counted in *refused (when given); the others go on.
  // Rows are stepped in order, so consecutive rows that continue one another
  // continue CVODE warm exactly as separate Run calls of one step would.
  std::vector<Vec6> StepEach(const std::vector<Vec6>& x, const std::vector<Valves>& u,
                             const PlantParams& params, double dt = 1.0, long* refused = nullptr);

  // Summed rewards of the balance rule (BalanceValves) in closed loop: row n
  // from levels x[n] for steps[n] steps of dt seconds under params, each
  // step's valves from the levels the step before left. Stuck valves are
  // applied in place of the commands and the reward charges the commanded
  // ones, as the plant's runner does; a step after which Plant::IsTerminal
  // holds is followed by full tanks, as in Run. A row the integrator refuses
  // (chattering), or whose levels are not finite, sums to -infinity from its
  // first such step on and is counted once in *refused (when given). Each
  // row's steps run in turn, so held valves continue CVODE warm. Throws
  // std::invalid_argument for a negative step count, dt <= 0 or band < 0.
  std::vector<double> RunBalanceRule(const std::vector<Vec6>& x, const std::vector<int>& steps,
                                     const PlantParams& params, const StuckValves& stuck,
                                     double band, double dt = 1.0, long* refused = nullptr);

 private:
  StepResult StepOnce(const Vec6& x, const Valves& u, const PlantParams& p, double dt,
                      RolloutResult* result);

  StepIntegrator integrator_;
  LinearStepper linear_;
  RolloutOptions options_;
};

}  // namespace ftc
