// Hybrid vector field of the six-tank fuel plant (plant-model.md, "Dynamics").
//
//   dx_i/dt = (q_in_i - q_out_i - s_i) / c_i
//
// A Mode freezes the discrete decisions (which pumps are live, which open
// tanks are sources, sinks or pinned empties); within a mode the field is
// affine in x, hence smooth for the integrator. Every root function is
// positive while its mode stays valid and reaches zero, decreasing, where the
// mode must be recomputed; ComputeMode applies the matching test with the
// boundary itself on the side the crossing leads to, so a located root always
// yields the new mode.
//
// A sink off the bottom (pumping, not pinned) relaxes towards its equilibrium
// level x_eq = x_ref - want * R / g, at which its inflow g (x_ref - x) / R
// equals its pump draw (time constant c R / g, 10 s nominal): it is filled
// while x_eq > x and drains while x_eq < x, and it can reach 0 only once x_eq
// is below 0, where ComputeMode pins it. Where the inflow exceeds the draw
// only marginally (e.g. an empty tank whose draw is what a pinned tank
// upstream leaves of the demand, near inflow = draw), the tank rises by some
// 1e-12 m for some 1e-5 s and returns: far below what CVODE resolves at the
// rollouts' atol of 1e-8. Its first step overshoots the excursion, the
// interpolated level crosses -kRootOffset within ~1e-7 s, the restart at 0
// finds the same mode (inflow still > draw), and so on: over 1000 switches in
// 1e-5 s, the oracle's "chattering" (tests/cpp/test_integrator.cpp). So a
// level below 0 counts as reached only if the tank drains there; while it is
// filled the level root is min(x_eq, -x) (continuous at x = 0, and positive
// until x_eq has fallen below 0). Wherever x >= 0 or the tank drains the root
// is the bare level, as before (every ordinary return to 0, and every point
// the closed-form steps of linear_step.cpp sample); and at a located root
// x_eq <= -kRootOffset, so the inflow at x = 0 is below the draw and
// ComputeMode pins the tank: the located root always changes the mode.
//
// A member that leaves a tied group (its pump outruns the group) becomes a
// sink at the group's level, within kTieTolerance of it and often one ulp
// above or below. The ordinary sink root, its gap x_ref - x_k below the group,
// starts there in the levels' rounding noise: CVODE's first steps see it cross
// 0 on noise, and a restart can leave the tank one ulp above the group, the
// root below 0 and so never watched (roots fire falling only). Where the
// tank's dip below the group is short (check/noise-10: 1e-9 m deep, 1.5 ms
// long) its rejoining was then never located, and the tank stayed above the
// group as a sink, 1e-4 m off within a step. So the root of such a sink
// (Mode::left) is the condition that made it leave: s_k - c_k rho', with rho'
// the rate of the group with the tank back in it. It is positive where the
// mode starts (that is why the tank left), and the gap can return to 0 only
// once it is not (the gap's rate is (s_k/c_k - rho_G') minus a positive
// multiple of the gap, and s_k/c_k - rho_G' has its sign, rho_G' the group's
// rate without the tank's inflow). Where it reaches 0 the tank is at most
// its dip below the group: ComputeMode takes it back into the group if that
// is within kTieTolerance (the model's resolution of a tie), else keeps it
// as an ordinary sink whose gap root is then clear of the noise.
#include "plant/core/dynamics.h"

#include <algorithm>
#include <cstdint>
#include <limits>

namespace ftc {
namespace {

// A member leaves the group when its own draw exceeds its share of the group
// rate by more than this fraction of the draw (plant-model.md: strictly
// faster). The margin keeps a member whose draw equals the group rate from
// leaving on a rounding error; its root function is offset by twice the
// margin, so a located crossing always makes the member leave.
constexpr double kLeaveMargin = 1e-12;

// Offset (m, m^3/s) on the level and pinned root functions, so that they are
// never exactly 0 when CVODE (re)starts: CVODE deactivates a root function
// that is 0 at the initial point and would miss its crossing.
constexpr double kRootOffset = 1e-15;

// Everything the field, the flows and the root functions need at x under a mode.
struct Evaluation {
  Flows flows;
  Vec6 derivative = Vec6::Zero();
  Vec6 want = Vec6::Zero();  // min(p_i, remaining demand) each pump would draw
  double xref = 0;           // level of the source group (conduit potential / g)
  double rho = 0;            // common fall rate of the source group, m/s
  double group_draw = 0;     // pumped by the source group, m^3/s
  double group_area = 0;     // the source group's cross-section, m^2
  bool any_sink = false;
  int group_size = 0;
};

Evaluation Evaluate(const Vec6& x, const PlantParams& p, const Mode& mode) {
  Evaluation e;
  double xref = -std::numeric_limits<double>::infinity();
  for (int i = 0; i < kTanks; ++i) {
    if (mode.source[i]) {
      xref = std::max(xref, x[i]);
      ++e.group_size;
    }
    e.any_sink = e.any_sink || mode.sink[i];
  }
  e.xref = e.group_size > 0 ? xref : 0.0;

  // Sinks receive (V - phi_k) / R_k; pinned tanks are sinks too.
  double inflow_total = 0;
  for (int i = 0; i < kTanks; ++i) {
    if (mode.sink[i]) {
      e.flows.conduit[i] = p.g * (e.xref - x[i]) / p.resistance[i];
      inflow_total += e.flows.conduit[i];
    }
  }

  // Pumps, innermost first; min(p, remaining) is evaluated at x so that a
  // pinned tank's varying supply passes its remainder on continuously. No
  // clamping here: inside the mode the values are in range by construction,
  // and where CVODE probes past a root a clamp would put a kink in the field
  // (and fuel out of balance) just before the root it is locating.
  for (int j = 0; j < kEngines; ++j) {
    double remaining = p.demand[j];
    for (const int i : kPumpOrder[j]) {
      const double want = std::min(p.pump[i], remaining);
      e.want[i] = want;
      double s = 0;
      if (mode.pinned[i]) {
        s = e.flows.conduit[i];  // all of the inflow (< want inside the mode)
      } else if (mode.pumping[i]) {
        s = want;
      }
      e.flows.supply[i] = s;
      remaining -= s;
    }
    e.flows.deficit[j] = remaining;
  }

  // The source group falls together and pays for the sinks' inflow.
  if (e.group_size > 0) {
    double draw = 0, area = 0;
    for (int i = 0; i < kTanks; ++i) {
      if (mode.source[i]) {
        draw += e.flows.supply[i];
        area += p.area[i];
      }
    }
    e.rho = (inflow_total + draw) / area;
    e.group_draw = draw;
    e.group_area = area;
    for (int i = 0; i < kTanks; ++i) {
      if (mode.source[i]) e.flows.conduit[i] = -(p.area[i] * e.rho - e.flows.supply[i]);
    }
  }

  for (int i = 0; i < kTanks; ++i) {
    if (mode.source[i]) {
      e.derivative[i] = -e.rho;  // exactly equal, so tied members stay tied
    } else {
      e.derivative[i] = (e.flows.conduit[i] - e.flows.supply[i]) / p.area[i];
    }
  }
  return e;
}

}  // namespace

Mode ComputeMode(const Vec6& x, const Valves& u, const PlantParams& p) {
  Mode m;
  int open = 0;
  double xmax = -std::numeric_limits<double>::infinity();
  for (int i = 0; i < kTanks; ++i) {
    if (u[i] != 0) {
      ++open;
      xmax = std::max(xmax, x[i]);
    }
  }
  // One open tank has nobody to exchange with: the conduit is idle.
  const bool conduit = open >= 2;
  Vec6 inflow = Vec6::Zero();
  if (conduit) {
    for (int i = 0; i < kTanks; ++i) {
      if (u[i] == 0) continue;
      if (x[i] >= xmax - kTieTolerance) {
        m.source[i] = true;
      } else {
        m.sink[i] = true;
        inflow[i] = p.g * (xmax - x[i]) / p.resistance[i];
      }
    }
  }

  for (int j = 0; j < kEngines; ++j) {
    double remaining = p.demand[j];
    for (const int i : kPumpOrder[j]) {
      const double want = std::max(0.0, std::min(p.pump[i], remaining));
      double s = 0;
      if (x[i] > 0) {
        m.pumping[i] = true;
        s = want;
      } else if (m.sink[i] && inflow[i] > 0) {
        // Equality counts as pinned: the inflow can only fall within a step
        // (the group level never rises), so the tank cannot rise.
        if (inflow[i] <= want) {  // stays at 0, passing its inflow to the pump
          m.pinned[i] = true;
          s = inflow[i];
        } else {  // fills faster than it is drawn: rises off the bottom
          m.pumping[i] = true;
          s = want;
        }
      }
      m.pump_draw[i] = s;
      remaining -= s;
    }
    m.deficit[j] = std::max(0.0, remaining);
  }

  // A group member whose own pump outruns the group leaves it and becomes a
  // sink. Leaving only lowers the group rate, so dropping every offender per
  // pass converges; the member with the smallest draw per area (<= rho) never
  // leaves, so the group never empties. A member that draws nothing cannot
  // outrun anything: where a sink sits a rounding error above the group (a
  // tie broken by one ulp), its inflow, and so rho, is slightly negative, and
  // without that test such a member left and emptied the group (found by the
  // closed-form steps of linear_step.cpp; test_dynamics.cpp).
  if (conduit) {
    for (;;) {
      double xref = -std::numeric_limits<double>::infinity();
      for (int i = 0; i < kTanks; ++i)
        if (m.source[i]) xref = std::max(xref, x[i]);
      double inflow_total = 0, draw = 0, area = 0;
      for (int i = 0; i < kTanks; ++i) {
        if (m.sink[i]) inflow_total += p.g * (xref - x[i]) / p.resistance[i];
        if (m.source[i]) {
          draw += m.pump_draw[i];
          area += p.area[i];
        }
      }
      const double rho = (inflow_total + draw) / area;
      bool changed = false;
      for (int i = 0; i < kTanks; ++i) {
        const double s = m.pump_draw[i];
        if (m.source[i] && s > 0 && s - p.area[i] * rho > kLeaveMargin * s) {
          m.source[i] = false;
          m.sink[i] = true;
          m.left[i] = true;
          changed = true;
        }
      }
      if (!changed) break;
    }
  }
  return m;
}

Flows ComputeFlows(const Vec6& x, const Valves& /*u*/, const PlantParams& p, const Mode& mode) {
  return Evaluate(x, p, mode).flows;
}

Vec6 Derivative(const Vec6& x, const Valves& /*u*/, const PlantParams& p, const Mode& mode) {
  return Evaluate(x, p, mode).derivative;
}

void EvaluateField(const Vec6& x, const PlantParams& p, const Mode& mode, Vec6* derivative,
                   Flows* flows) {
  Evaluation e = Evaluate(x, p, mode);
  *derivative = e.derivative;
  *flows = e.flows;
}

namespace {

// The root slots in force at an evaluation (bit m: slot m is a function of x;
// the others are held at 1). Slot i: a draining tank reaching the bottom (a
// live pump, or a source member paying for sinks); slot kTanks + i: the
// tank's place in the conduit changes (pinned, sink, or a source member whose
// own pump may outrun the group).
std::uint32_t ActiveRoots(const Evaluation& e, const Mode& mode) {
  std::uint32_t active = 0;
  for (int i = 0; i < kTanks; ++i) {
    if (!mode.pinned[i] && (mode.pumping[i] || (mode.source[i] && e.any_sink && e.rho > 0)))
      active |= 1u << i;
    if (mode.pinned[i] || mode.sink[i] ||
        (mode.source[i] && e.any_sink && e.flows.supply[i] > 0))
      active |= 1u << (kTanks + i);
  }
  return active;
}

std::array<double, kNumRoots> RootsOf(const Evaluation& e, const Vec6& x, const PlantParams& p,
                                      const Mode& mode, std::uint32_t active) {
  std::array<double, kNumRoots> r;
  r.fill(1.0);
  for (int i = 0; i < kTanks; ++i) {
    // A sink's level below 0 while it is still being filled is an integration
    // error, not the bottom (file header).
    if (active & (1u << i)) {
      double bottom = x[i];
      if (mode.sink[i] && x[i] < 0) {
        const double equilibrium = e.xref - e.want[i] * p.resistance[i] / p.g;
        if (equilibrium > x[i]) bottom = std::min(equilibrium, -x[i]);
      }
      r[i] = bottom + kRootOffset;
    }
    if (!(active & (1u << (kTanks + i)))) continue;
    double& b = r[kTanks + i];
    if (mode.pinned[i]) {
      b = e.want[i] - e.flows.conduit[i] + kRootOffset;  // inflow exceeds the pump draw
    } else if (mode.left[i]) {
      // Its pump no longer outruns the group it would rejoin (file header).
      // Half ComputeMode's margin: where this is <= 0 the tank stays in the
      // group, and where the tank left it is at least half the margin.
      const double s = e.flows.supply[i];
      double others = 0;  // the other sinks' inflow
      for (int k = 0; k < kTanks; ++k)
        if (k != i && mode.sink[k]) others += e.flows.conduit[k];
      const double rho = (others + e.group_draw + s) / (e.group_area + p.area[i]);
      b = s - p.area[i] * rho - 0.5 * kLeaveMargin * s;
    } else if (mode.sink[i]) {
      b = e.xref - x[i];  // rises to the conduit level: joins the group
    } else if (mode.source[i]) {
      const double s = e.flows.supply[i];  // own pump outruns the group:
      b = p.area[i] * e.rho - s + 2 * kLeaveMargin * s;
    }
  }
  return r;
}

}  // namespace

std::array<double, kNumRoots> RootFunctions(const Vec6& x, const Valves& /*u*/,
                                            const PlantParams& p, const Mode& mode) {
  const Evaluation e = Evaluate(x, p, mode);
  return RootsOf(e, x, p, mode, ActiveRoots(e, mode));
}

std::array<double, kNumRoots> RootFunctionsOf(const Vec6& x, const PlantParams& p,
                                              const Mode& mode, std::uint32_t active) {
  return RootsOf(Evaluate(x, p, mode), x, p, mode, active);
}

void FieldAndRoots(const Vec6& x, const PlantParams& p, const Mode& mode, Vec6* derivative,
                   std::array<double, kNumRoots>* roots, std::uint32_t* active) {
  const Evaluation e = Evaluate(x, p, mode);
  *active = ActiveRoots(e, mode);
  *derivative = e.derivative;
  *roots = RootsOf(e, x, p, mode, *active);
}

}  // namespace ftc
