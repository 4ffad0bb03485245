// Closed-form steps with the conduit active (see linear_step.h).
//
// Coordinates of a mode. The conduit's nodes are the source group (its tanks
// move together: the direction is 1 on every source) and each sink (a unit
// vector); every other tank falls at a constant rate (its pump, or nothing).
// Along those directions the field and the root functions are affine, so one
// evaluation at x and one per direction, with a unit step, give M, b and the
// roots' gradients exactly up to rounding.
#include "plant/core/linear_step.h"

// GCC 12 reports maybe-uninitialized inside Eigen's eigensolver for
// fixed-capacity matrices (a false positive; the solver writes before reading)
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#include <Eigen/Eigenvalues>
#include <Eigen/LU>
#pragma GCC diagnostic pop

#include <algorithm>
#include <array>
#include <memory>
#include <cmath>
#include <stdexcept>
#include <string>

#include "plant/core/dynamics.h"

namespace ftc {
namespace {

// Samples per segment at which the root functions' signs are checked (CVODE
// checks at its own steps: 1-12 per second).
constexpr int kGrid = 8;
// Bisection of a bracketed root stops at this width (s): rounding of t.
constexpr double kRootWidth = 1e-14;

using NodeMatrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, kTanks, kTanks>;
using NodeVector = Eigen::Matrix<double, Eigen::Dynamic, 1, 0, kTanks, 1>;
using RootMatrix = Eigen::Matrix<double, kNumRoots, Eigen::Dynamic, 0, kNumRoots, kTanks>;
using RootVector = Eigen::Matrix<double, kNumRoots, 1>;

// (e^{lambda t} - 1) / lambda, and t where lambda is 0.
double Psi(double lambda, double t) { return lambda == 0.0 ? t : std::expm1(lambda * t) / lambda; }

RootVector AsVector(const std::array<double, kNumRoots>& r) {
  return Eigen::Map<const RootVector>(r.data());
}

// One mode's closed form: x(t) = x0 + rate t + D (P (psi(t) .* a)), where D
// spreads the conduit nodes back onto the tanks, and the root functions
// g(t) = g0 + L t + K psi(t).
class ModeSolution {
 public:
  // Prepares the mode at x, reusing the last preparation if the mode, valves
  // and parameters are the same (M, its eigenvectors and the roots' gradients
  // do not depend on x within a mode). Returns false where the mode is not
  // handled (a pinned tank upstream of a pump that cannot cover its engine's
  // demand) or M has no real, well-conditioned eigenbasis.
  bool Build(const Vec6& x, const Valves& u, const PlantParams& p, const Mode& mode) {
    psi_t_ = -1;  // the memo of Psi (below) is the last mode's
    if (prepared_ && SameMode(mode) && u == valves_ && SameParams(p, params_)) {
      Start(x, Derivative(x, u, p, mode), AsVector(RootFunctions(x, u, p, mode)));
      return true;
    }
    prepared_ = false;
    Vec6 f0;
    RootVector g0;
    if (!Prepare(x, u, p, mode, &f0, &g0)) return false;
    mode_ = mode;
    valves_ = u;
    params_ = p;
    prepared_ = true;
    Start(x, f0, g0);  // the field and roots at x, as Prepare evaluated them
    return true;
  }

  // Whether no root function can end the mode within [0, t] (checked on the
  // grid in Step): each term of g(t) = g0 + L t + sum_k K_k psi_k(t) is monotone
  // in t from 0 (psi_k' = e^{lambda_k t} > 0), so g lies between g0 plus the
  // negative and g0 plus the positive terms at t. A watched function bounded
  // above 0, or an unwatched one bounded below 0 (never armed), cannot be seen
  // crossing at any grid time; the margin covers the rounding of g's
  // evaluation (a few ulps of its terms' magnitude). Not finite: not proven.
  bool NoCrossingWithin(double t) {
    const NodeVector& psi = PsiAt(t);
    for (int m = 0; m < kNumRoots; ++m) {
      const double lin = linear_[m] * t;
      double low = g0_[m] + std::min(0.0, lin), high = g0_[m] + std::max(0.0, lin);
      double size = std::abs(g0_[m]) + std::abs(lin);
      for (int k = 0; k < nodes_; ++k) {
        const double term = roots_(m, k) * psi[k];
        low += std::min(0.0, term);
        high += std::max(0.0, term);
        size += std::abs(term);
      }
      const double margin = 1e-10 * size;
      const bool above = low > margin;
      const bool below = watched_[m] == 0.0 && high < -margin;
      if (!(above || below)) return false;
    }
    return true;
  }

  // Whether a watched root function is <= 0 at t (the values into *values if given).
  bool Crossed(double t, RootVector* values = nullptr) const {
    const RootVector g = Roots(t);
    if (values != nullptr) *values = g;
    return ((g.array() <= 0.0).cast<double>() * watched_.array()).any();
  }

  bool Watched(int slot) const { return watched_[slot] != 0.0; }

  // Watches the functions positive in g (values at a time before any crossing):
  // as CVODE reactivates a root function that was 0 (or below) at a restart
  // once it has moved above 0, a later downward crossing of it ends the mode
  // too (e.g. a sink that left a tied group at its start and catches up with
  // the group within the step).
  void Arm(const RootVector& g) { watched_ = (g.array() > 0.0).cast<double>(); }

  Vec6 Levels(double t) const {
    const NodeVector moved = spread_ * Psi(t);
    Vec6 x = x0_ + rate_ * t;
    for (int i = 0; i < kTanks; ++i)
      if (node_of_[i] >= 0) x[i] += moved[node_of_[i]];
    return x;
  }

  RootVector Roots(double t) const { return g0_ + linear_ * t + roots_ * Psi(t); }

  // Root function m alone at t.
  double Root(int m, double t) const { return g0_[m] + linear_[m] * t + roots_.row(m).dot(Psi(t)); }

  bool SameMode(const Mode& m) const {
    return m.source == mode_.source && m.sink == mode_.sink && m.pinned == mode_.pinned &&
           m.pumping == mode_.pumping;
  }

  // What does not depend on x within the mode: the nodes, M's eigenvectors, the
  // root functions' gradients along the nodes and the tanks off the conduit.
  bool Prepare(const Vec6& x, const Valves& u, const PlantParams& p, const Mode& mode,
               Vec6* field, RootVector* roots) {
    nodes_ = 0;
    node_of_.fill(-1);
    // A pinned tank passes its inflow (affine in the group level) to its engine,
    // and each pump after it in the engine's order draws min(p, remaining): affine
    // only while that pump could cover the whole demand. Other cases: CVODE.
    for (int j = 0; j < kEngines; ++j) {
      bool after_pinned = false;
      for (const int i : kPumpOrder[j]) {
        if (after_pinned && p.pump[i] < p.demand[j]) return false;
        after_pinned = after_pinned || mode.pinned[i];
      }
    }
    NodeVector area(kTanks);
    double group_area = 0;
    for (int i = 0; i < kTanks; ++i) {
      if (mode.source[i]) {
        node_of_[i] = 0;
        group_area += p.area[i];
        if (nodes_ == 0) representative_[nodes_++] = i;
      }
    }
    if (nodes_ == 0) return false;  // no conduit
    area[0] = group_area;
    for (int i = 0; i < kTanks; ++i) {
      if (mode.sink[i] && !mode.pinned[i]) {  // a pinned tank stays at 0: no node
        node_of_[i] = nodes_;
        area[nodes_] = p.area[i];
        representative_[nodes_++] = i;
      }
    }
    const int conduit_nodes = nodes_;

    // The field along each node's direction (sources together, each sink alone).
    const Vec6 f0 = Derivative(x, u, p, mode);
    const RootVector g0 = AsVector(RootFunctions(x, u, p, mode));
    *field = f0;
    *roots = g0;
    auto direction = [&](int d) {
      Vec6 moved = x;
      for (int i = 0; i < kTanks; ++i)
        if (node_of_[i] == d) moved[i] += 1.0;
      return moved;
    };
    Eigen::Matrix<double, kTanks, kTanks> df;
    for (int d = 0; d < conduit_nodes; ++d) df.col(d) = Derivative(direction(d), u, p, mode) - f0;
    // A tank off the conduit whose pump passes on what a pinned tank upstream does
    // not supply moves with the group: a node too (it does not act back).
    for (int i = 0; i < kTanks; ++i) {
      if (node_of_[i] >= 0 || mode.pinned[i]) continue;
      if ((df.row(i).head(conduit_nodes).array() != 0.0).any()) {
        node_of_[i] = nodes_;
        area[nodes_] = p.area[i];
        representative_[nodes_++] = i;
      }
    }
    area.conservativeResize(nodes_);
    NodeMatrix m = NodeMatrix::Zero(nodes_, nodes_);
    root_nodes_.resize(kNumRoots, nodes_);
    for (int d = 0; d < nodes_; ++d) {
      const Vec6 moved = direction(d);
      if (d >= conduit_nodes) df.col(d) = Derivative(moved, u, p, mode) - f0;
      for (int k = 0; k < nodes_; ++k) m(k, d) = df(representative_[k], d);
      for (int i = 0; i < kTanks; ++i)
        if (node_of_[i] < 0 && df(i, d) != 0.0) return false;  // not affine as assumed
      root_nodes_.col(d) = AsVector(RootFunctions(moved, u, p, mode)) - g0;
    }
    // Tanks off the conduit fall at their constant rate: a direction each.
    root_off_.setZero();
    for (int i = 0; i < kTanks; ++i) {
      if (node_of_[i] >= 0 || f0[i] == 0.0) continue;
      Vec6 moved = x;
      moved[i] += 1.0;
      root_off_.col(i) = AsVector(RootFunctions(moved, u, p, mode)) - g0;
    }
    return Decompose(m, area);
  }

  // M = V diag(lambda) V^-1 with real lambda. Usually M = C^-1 L (a star of
  // conductances): C^1/2 M C^-1/2 is symmetric, and its eigenvectors give V
  // at once. With a driven tank (above) M is not of that kind: a general
  // eigendecomposition, accepted if its eigenvalues are real and V is well
  // conditioned (else CVODE integrates the mode).
  bool Decompose(const NodeMatrix& m, const NodeVector& area) {
    const NodeVector root_area = area.cwiseSqrt();
    NodeMatrix s(nodes_, nodes_);
    double largest = 0, asymmetry = 0;
    for (int i = 0; i < nodes_; ++i)
      for (int j = 0; j < nodes_; ++j) {
        s(i, j) = root_area[i] * m(i, j) / root_area[j];
        largest = std::max(largest, std::abs(s(i, j)));
      }
    for (int i = 0; i < nodes_; ++i)
      for (int j = 0; j < i; ++j) {
        asymmetry = std::max(asymmetry, std::abs(s(i, j) - s(j, i)));
        s(i, j) = s(j, i) = 0.5 * (s(i, j) + s(j, i));
      }
    if (asymmetry <= 1e-12 * largest) {
      const Eigen::SelfAdjointEigenSolver<NodeMatrix> eigen(s);
      if (eigen.info() != Eigen::Success) return false;
      lambda_ = eigen.eigenvalues();
      vectors_ = root_area.cwiseInverse().asDiagonal() * eigen.eigenvectors();
      inverse_ = eigen.eigenvectors().transpose() * root_area.asDiagonal();
      return true;
    }
    const Eigen::EigenSolver<NodeMatrix> eigen(m);
    if (eigen.info() != Eigen::Success) return false;
    const double scale = std::max(m.cwiseAbs().maxCoeff(), 1e-300);
    if (eigen.eigenvalues().imag().cwiseAbs().maxCoeff() > 1e-12 * scale) return false;
    lambda_ = eigen.eigenvalues().real();
    vectors_ = eigen.eigenvectors().real();
    const Eigen::FullPivLU<NodeMatrix> lu(vectors_);
    if (lu.rcond() < 1e-8) return false;  // nearly defective: no good eigenbasis
    inverse_ = lu.inverse();
    return true;
  }

  // The solution from x: f0 and g0 are the field and the root functions there.
  void Start(const Vec6& x, const Vec6& f0, const RootVector& g0) {
    x0_ = x;
    g0_ = g0;
    rate_.setZero();
    for (int i = 0; i < kTanks; ++i)
      if (node_of_[i] < 0) rate_[i] = f0[i];
    linear_ = root_off_ * rate_;
    NodeVector f_nodes(nodes_);
    for (int k = 0; k < nodes_; ++k) f_nodes[k] = f0[representative_[k]];
    const NodeVector a = inverse_ * f_nodes;
    spread_ = vectors_ * a.asDiagonal();
    roots_ = root_nodes_ * spread_;
    // As CVODE at a restart: a function not positive where the mode begins is
    // not watched (the level roots carry an offset so that an empty tank's is)
    watched_ = (g0_.array() > 0.0).cast<double>();
    // A function exactly at 0 that rises at once (a member that leaves a tied
    // group, its root x_lead - x_k at 0) is watched from the start: CVODE's first
    // internal step, a fraction of the grid's, sees it above 0 and reactivates it,
    // so its return to 0 (the member catching up with the group) is an event.
    for (int m = 0; m < kNumRoots; ++m)
      if (g0_[m] == 0.0 && linear_[m] + roots_.row(m).sum() > 0.0) watched_[m] = 1.0;
  }

 private:
  // psi(t), kept for the last t asked (the grid's and the root search's times
  // recur: the bracket's ends, the levels where the step stops)
  const NodeVector& PsiAt(double t) const {
    if (t != psi_t_) {
      psi_.resize(nodes_);
      for (int k = 0; k < nodes_; ++k) psi_[k] = ftc::Psi(lambda_[k], t);
      psi_t_ = t;
    }
    return psi_;
  }
  const NodeVector& Psi(double t) const { return PsiAt(t); }

  // the preparation and what it was for
  bool prepared_ = false;
  Mode mode_;
  Valves valves_ = Valves::Zero();
  PlantParams params_;
  int nodes_ = 0;
  std::array<int, kTanks> node_of_{};
  int representative_[kTanks] = {};
  NodeVector lambda_;
  NodeMatrix vectors_, inverse_;  // M = vectors_ diag(lambda_) inverse_
  RootMatrix root_nodes_;
  Eigen::Matrix<double, kNumRoots, kTanks> root_off_;
  // the solution from x0_
  Vec6 x0_, rate_;
  NodeMatrix spread_;  // node displacement per psi
  RootVector g0_, linear_, watched_;
  RootMatrix roots_;
  mutable double psi_t_ = -1;  // the time psi_ is for (-1: none)
  mutable NodeVector psi_;
};

}  // namespace

struct LinearStepper::Impl {
  ModeSolution solution;
};

LinearStepper::LinearStepper() : impl_(std::make_unique<Impl>()) {}

LinearStepper::~LinearStepper() = default;

LinearStepResult LinearConduitStep(const Vec6& x0, const Valves& u, const PlantParams& p,
                                   double dt, int max_events) {
  LinearStepper stepper;
  return stepper.Step(x0, u, p, dt, max_events);
}

LinearStepResult LinearStepper::Step(const Vec6& x0, const Valves& u, const PlantParams& p,
                                     double dt, int max_events) {
  LinearStepResult r;
  r.x = x0;
  ClampLevels(r.x.data(), p.height);
  ModeSolution& solution = impl_->solution;
  while (r.t < dt) {
    const Mode mode = ComputeMode(r.x, u, p);
    if (!solution.Build(r.x, u, p, mode)) return r;  // the caller integrates the rest
    const double remaining = dt - r.t;
    if (solution.NoCrossingWithin(remaining)) {  // the grid would find nothing
      r.x = solution.Levels(remaining);
      r.t = dt;
      break;
    }
    // The first grid interval in which a root function falls to <= 0.
    double lo = 0, hi = remaining;
    RootVector at_lo, at_hi;  // the root functions at the bracket's ends
    bool found = false;
    for (int k = 1; k <= kGrid && !found; ++k) {
      const double t = remaining * k / kGrid;
      RootVector g;
      if (solution.Crossed(t, &g)) {
        hi = t;
        at_hi = g;
        found = true;
      } else {
        lo = t;
        at_lo = g;
        solution.Arm(g);
      }
    }
    if (!found) {
      r.x = solution.Levels(remaining);
      r.t = dt;
      break;
    }
    // The earliest crossing in (lo, hi]: each watched function that is <= 0 at
    // hi is located by the Illinois method (regula falsi that halves the value
    // kept at an end that stays put) to the bracket width; the earliest wins.
    if (lo == 0) at_lo = solution.Roots(0);
    double first_lo = lo, first_hi = hi;
    for (int m = 0; m < kNumRoots; ++m) {
      if (!solution.Watched(m) || at_hi[m] > 0.0) continue;
      double a = lo, b = first_hi, fa = at_lo[m], fb = solution.Root(m, b);
      if (fb > 0.0) continue;  // crosses after the earliest found so far
      int kept = 0;            // the end that moved last: -1 a, +1 b
      for (int iteration = 0; b - a > kRootWidth * std::max(1.0, b); ++iteration) {
        // (after 60 false-position steps, bisection: at most 60 more to the width)
        double c = iteration < 60 ? (a * fb - b * fa) / (fb - fa) : 0.5 * (a + b);
        if (!(c > a && c < b)) c = 0.5 * (a + b);
        const double fc = solution.Root(m, c);
        if (fc <= 0.0) {
          b = c;
          fb = fc;
          if (kept == 1) fa *= 0.5;
          kept = 1;
        } else {
          a = c;
          fa = fc;
          if (kept == -1) fb *= 0.5;
          kept = -1;
        }
      }
      first_lo = a;
      first_hi = b;
    }
    lo = first_lo;
    hi = first_hi;
    RootVector g;
    solution.Crossed(hi, &g);
    r.x = solution.Levels(hi);
    for (int i = 0; i < kTanks; ++i)
      if (solution.Watched(i) && g[i] <= 0.0) r.x[i] = 0.0;  // located at its bottom: empty
    ClampLevels(r.x.data(), p.height);
    r.t = hi >= remaining ? dt : r.t + hi;
    if (++r.events > max_events) {
      throw std::runtime_error("LinearConduitStep: more than " + std::to_string(max_events) +
                               " mode switches in one step (chattering)");
    }
  }
  ClampLevels(r.x.data(), p.height);
  return r;
}

}  // namespace ftc
