// Batch rollouts for planners (see rollout.h).
//
// Cost model (Debian's SUNDIALS is built -O0): a CVODE step that restarts
// (new valves or state) costs ~30 us, a warm continuation with valves held
// ~7 us. A planner's candidates are mostly "an action held for H steps, then
// all valves closed", so two things make a batch cheap:
//  * closed (or single-open) valves leave the conduit idle, and the field is
//    then piecewise constant: each live pump draws a fixed rate until a tank
//    runs dry. Those steps are solved exactly (IdleConduitStep), no CVODE;
//  * candidates are simulated in lexicographic order of their valve codes,
//    so a prefix shared with the previous candidate (the longest shared with
//    any earlier one) is taken from a stack of states instead of recomputed.
// Within a candidate, held valves continue CVODE warm (StepIntegrator).
#include "plant/core/rollout.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <numeric>
#include <stdexcept>
#include <string>

#include "plant/core/plant.h"
#include "plant/core/reward.h"

namespace ftc {
namespace {

int OpenCount(const Valves& u) { return static_cast<int>((u.array() != 0).count()); }

std::uint8_t Code(const Valves& u) {
  std::uint8_t c = 0;
  for (int i = 0; i < kTanks; ++i)
    if (u[i] != 0) c = static_cast<std::uint8_t>(c | (1u << i));
  return c;
}

}  // namespace

StepResult IdleConduitStep(const Vec6& x0, const Valves& u, const PlantParams& p, double dt) {
  if (OpenCount(u) >= 2)
    throw std::invalid_argument("IdleConduitStep: two or more valves open (conduit active)");
  StepResult r;
  Vec6 x = x0.cwiseMax(0.0).cwiseMin(p.height);
  for (int i = 0; i < kTanks; ++i)
    if (x[i] < kEmptySnap) x[i] = 0.0;
  double t = 0;
  // Each segment ends when a pumping tank runs dry (at most one per tank) or at dt.
  for (int segment = 0; segment <= kTanks; ++segment) {
    const Mode mode = ComputeMode(x, u, p);
    Vec6 dx;
    Flows flows;
    EvaluateField(x, p, mode, &dx, &flows);
    double tau = dt - t;
    int dry = -1;
    for (int i = 0; i < kTanks; ++i) {
      if (dx[i] < 0 && x[i] / -dx[i] < tau) {
        tau = x[i] / -dx[i];
        dry = i;
      }
    }
    x += dx * tau;
    r.supplied += flows.supply * tau;
    r.deficit += flows.deficit * tau;
    t += tau;
    if (dry < 0) break;
    x[dry] = 0.0;  // exactly empty, as the integrator sets a located root
    for (int i = 0; i < kTanks; ++i)
      if (x[i] < kEmptySnap) x[i] = 0.0;
    ++r.events;
  }
  r.x = x.cwiseMax(0.0);
  return r;
}

Valves BalanceValves(const Vec6& x, const PlantParams& p, double band) {
  Valves u = Valves::Zero();
  const Vec6 mass = p.area.cwiseProduct(x.cwiseMax(0.0));
  const double total = mass.sum();
  if (!(total > 0)) return u;  // no fuel (or NaN levels): nothing to balance
  const double cg = mass.dot(MomentArms()) / total;
  if (!(std::abs(cg) > band)) return u;
  // tanks 0-2 are the left wing, 3-5 the right; cg > 0: the right wing is heavy
  const int heavy = cg > 0 ? 3 : 0, light = cg > 0 ? 0 : 3;
  int source = heavy, sink = light;
  for (int i = 1; i < 3; ++i) {
    if (x[heavy + i] > x[source]) source = heavy + i;
    if (x[light + i] < x[sink]) sink = light + i;
  }
  u[source] = 1;
  u[sink] = 1;
  return u;
}

BatchRollout::BatchRollout(const IntegratorOptions& integrator, const RolloutOptions& options)
    : integrator_(integrator), options_(options) {}

StepResult BatchRollout::StepOnce(const Vec6& x, const Valves& u, const PlantParams& p,
                                  double dt, RolloutResult* result) {
  if (options_.exact_idle_conduit && OpenCount(u) < 2) {
    ++result->exact_steps;
    return IdleConduitStep(x, u, p, dt);
  }
  if (options_.exact_active_conduit) {
    const LinearStepResult linear = linear_.Step(x, u, p, dt);
    if (linear.t >= dt) {
      ++result->exact_steps;
      StepResult r;  // the levels only: a rollout's rewards need nothing else
      r.x = linear.x;
      r.events = linear.events;
      return r;
    }
    ++result->integrated_steps;  // the rest of the step, from where the closed form stopped
    StepResult r = integrator_.Step(linear.x, u, p, dt - linear.t);
    r.events += linear.events;
    return r;
  }
  ++result->integrated_steps;
  return integrator_.Step(x, u, p, dt);
}

RolloutResult BatchRollout::Run(const Vec6& x0, const std::vector<Valves>& sequences,
                                int num_candidates, int horizon,
                                const std::vector<PlantParams>& params, double dt) {
  if (num_candidates < 0 || horizon < 0)
    throw std::invalid_argument("BatchRollout::Run: negative number of candidates or steps");
  const std::size_t k_count = static_cast<std::size_t>(num_candidates);
  const std::size_t l_count = static_cast<std::size_t>(horizon);
  if (sequences.size() != k_count * l_count) {
    throw std::invalid_argument("BatchRollout::Run: " + std::to_string(sequences.size()) +
                                " valve settings for " + std::to_string(num_candidates) +
                                " x " + std::to_string(horizon));
  }
  if (params.size() != 1 && params.size() != l_count)
    throw std::invalid_argument("BatchRollout::Run: params must hold 1 or horizon sets");
  for (const Valves& u : sequences)
    if (((u.array() != 0) && (u.array() != 1)).any())
      throw std::invalid_argument("BatchRollout::Run: valves must be 0 or 1");

  RolloutResult out;
  out.total.assign(k_count, 0.0);
  out.rewards.assign(k_count * l_count, 0.0);
  out.levels.assign(k_count * l_count, Vec6::Zero());
  out.terminal.assign(k_count * l_count, 0);

  std::vector<std::uint8_t> codes(sequences.size());
  std::transform(sequences.begin(), sequences.end(), codes.begin(), Code);
  std::vector<std::size_t> order(k_count);
  std::iota(order.begin(), order.end(), 0);
  if (options_.share_prefixes) {
    std::stable_sort(order.begin(), order.end(), [&](std::size_t a, std::size_t b) {
      return std::lexicographical_compare(codes.begin() + a * l_count,
                                          codes.begin() + (a + 1) * l_count,
                                          codes.begin() + b * l_count,
                                          codes.begin() + (b + 1) * l_count);
    });
  }

  // state[d]: the level d steps in (after any reset); valid up to the previous
  // candidate's depth. reward/level/terminal[d]: its step d.
  std::vector<Vec6> state(l_count + 1, x0);
  std::vector<double> cum(l_count + 1, 0.0);
  std::size_t previous = k_count;  // none yet
  for (const std::size_t k : order) {
    std::size_t shared = 0;
    if (options_.share_prefixes && previous != k_count) {
      while (shared < l_count &&
             codes[k * l_count + shared] == codes[previous * l_count + shared])
        ++shared;
      for (std::size_t d = 0; d < shared; ++d) {
        out.rewards[k * l_count + d] = out.rewards[previous * l_count + d];
        out.levels[k * l_count + d] = out.levels[previous * l_count + d];
        out.terminal[k * l_count + d] = out.terminal[previous * l_count + d];
      }
      out.shared_steps += static_cast<long>(shared);
    }
    for (std::size_t d = shared; d < l_count; ++d) {
      const PlantParams& p = params.size() == 1 ? params[0] : params[d];
      const Valves& u = sequences[k * l_count + d];
      const StepResult r = StepOnce(state[d], u, p, dt, &out);
      const double rew = ComputeReward(r.x, u, p).reward;
      const bool terminal = Plant::IsTerminal(r.x, p, dt);
      out.rewards[k * l_count + d] = rew;
      out.levels[k * l_count + d] = r.x;
      out.terminal[k * l_count + d] = terminal ? 1 : 0;
      cum[d + 1] = cum[d] + rew;
      state[d + 1] = terminal ? Vec6(p.height) : r.x;
    }
    out.total[k] = cum[l_count];
    previous = k;
  }
  return out;
}

std::vector<Vec6> BatchRollout::StepEach(const std::vector<Vec6>& x, const std::vector<Valves>& u,
                                         const PlantParams& params, double dt, long* refused) {
  if (x.size() != u.size())
    throw std::invalid_argument("BatchRollout::StepEach: " + std::to_string(x.size()) +
                                " states for " + std::to_string(u.size()) + " valve settings");
  for (const Valves& v : u)
    if (((v.array() != 0) && (v.array() != 1)).any())
      throw std::invalid_argument("BatchRollout::StepEach: valves must be 0 or 1");
  std::vector<Vec6> out(x.size());
  RolloutResult counts;  // StepOnce's step counters; not reported here
  for (std::size_t n = 0; n < x.size(); ++n) {
    try {
      out[n] = StepOnce(x[n], u[n], params, dt, &counts).x;
    } catch (const std::runtime_error&) {
      out[n].setConstant(std::numeric_limits<double>::quiet_NaN());
      if (refused != nullptr) ++*refused;
    }
  }
  return out;
}

std::vector<double> BatchRollout::RunBalanceRule(const std::vector<Vec6>& x,
                                                 const std::vector<int>& steps,
                                                 const PlantParams& params,
                                                 const StuckValves& stuck, double band,
                                                 double dt, long* refused) {
  if (x.size() != steps.size())
    throw std::invalid_argument("BatchRollout::RunBalanceRule: " + std::to_string(x.size()) +
                                " states for " + std::to_string(steps.size()) + " step counts");
  if (std::any_of(steps.begin(), steps.end(), [](int s) { return s < 0; }))
    throw std::invalid_argument("BatchRollout::RunBalanceRule: negative number of steps");
  if (!(dt > 0) || !(band >= 0))
    throw std::invalid_argument("BatchRollout::RunBalanceRule: dt must be > 0 and band >= 0");
  std::vector<double> total(x.size(), 0.0);
  RolloutResult counts;  // StepOnce's step counters; not reported here
  for (std::size_t n = 0; n < x.size(); ++n) {
    Vec6 level = x[n];
    for (int t = 0; t < steps[n]; ++t) {
      const Valves commanded = BalanceValves(level, params, band);
      const Valves applied = stuck.Apply(commanded);
      StepResult r;
      bool stepped = true;
      try {
        r = StepOnce(level, applied, params, dt, &counts);
      } catch (const std::runtime_error&) {
        stepped = false;
      }
      if (!stepped || !r.x.allFinite()) {  // refused, or no levels to go on from
        total[n] = -std::numeric_limits<double>::infinity();
        if (refused != nullptr) ++*refused;
        break;
      }
      total[n] += ComputeReward(r.x, commanded, params).reward;
      level = Plant::IsTerminal(r.x, params, dt) ? Vec6(params.height) : r.x;
    }
  }
  return total;
}

}  // namespace ftc
