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
#pragma GCC diagnostic pop

#include <algorithm>
#include <array>
#include <cmath>
#include <stdexcept>
#include <string>

#include "plant/core/dynamics.h"

namespace ftc {
namespace {

// Levels below this (m) count as empty, as in the integrator's snap.
constexpr double kEmptySnap = 1e-12;
// Samples per segment at which the root functions' signs are checked (CVODE
// checks at its own steps: 1-12 per second).
constexpr int kGrid = 8;
// Bisection of a bracketed root stops at this width (s): rounding of t.
constexpr double kRootWidth = 1e-14;

using NodeMatrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, kTanks, kTanks>;
using NodeVector = Eigen::Matrix<double, Eigen::Dynamic, 1, 0, kTanks, 1>;
using RootMatrix = Eigen::Matrix<double, kNumRoots, Eigen::Dynamic, 0, kNumRoots, kTanks>;
using RootVector = Eigen::Matrix<double, kNumRoots, 1>;

void Clamp(Vec6* x, const PlantParams& p) {
  for (int i = 0; i < kTanks; ++i) {
    double v = std::clamp((*x)[i], 0.0, p.height[i]);
    if (v < kEmptySnap) v = 0.0;
    (*x)[i] = v;
  }
}

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
  // Returns false where the mode is not handled (a pinned tank) or M is not
  // the symmetric kind (never seen; CVODE then integrates).
  bool Build(const Vec6& x, const Valves& u, const PlantParams& p, const Mode& mode) {
    x0_ = x;
    nodes_ = 0;
    node_of_.fill(-1);
    for (int i = 0; i < kTanks; ++i)
      if (mode.pinned[i]) return false;
    double group_area = 0;
    int representative[kTanks];
    for (int i = 0; i < kTanks; ++i) {
      if (mode.source[i]) {
        node_of_[i] = 0;
        group_area += p.area[i];
        if (nodes_ == 0) representative[nodes_++] = i;
      }
    }
    if (nodes_ == 0) return false;  // no conduit
    NodeVector area(kTanks);
    area[0] = group_area;
    for (int i = 0; i < kTanks; ++i) {
      if (mode.sink[i]) {
        node_of_[i] = nodes_;
        area[nodes_] = p.area[i];
        representative[nodes_++] = i;
      }
    }
    area.conservativeResize(nodes_);

    const Vec6 f0 = Derivative(x, u, p, mode);
    const RootVector g0 = AsVector(RootFunctions(x, u, p, mode));
    NodeMatrix m(nodes_, nodes_);
    RootMatrix root_nodes(kNumRoots, nodes_);
    for (int d = 0; d < nodes_; ++d) {
      Vec6 moved = x;
      for (int i = 0; i < kTanks; ++i)
        if (node_of_[i] == d) moved[i] += 1.0;
      const Vec6 df = Derivative(moved, u, p, mode) - f0;
      for (int k = 0; k < nodes_; ++k) m(k, d) = df[representative[k]];
      for (int i = 0; i < kTanks; ++i)
        if (node_of_[i] < 0 && df[i] != 0.0) return false;  // off the conduit: constant
      root_nodes.col(d) = AsVector(RootFunctions(moved, u, p, mode)) - g0;
    }
    // Tanks off the conduit fall at their constant rate: one more direction each.
    rate_.setZero();
    linear_.setZero();
    for (int i = 0; i < kTanks; ++i) {
      if (node_of_[i] >= 0 || f0[i] == 0.0) continue;
      rate_[i] = f0[i];
      Vec6 moved = x;
      moved[i] += 1.0;
      linear_ += (AsVector(RootFunctions(moved, u, p, mode)) - g0) * f0[i];
    }
    // M = C^-1 L: C^1/2 M C^-1/2 is symmetric (checked to rounding).
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
    if (asymmetry > 1e-12 * largest) return false;
    const Eigen::SelfAdjointEigenSolver<NodeMatrix> eigen(s);
    if (eigen.info() != Eigen::Success) return false;
    lambda_ = eigen.eigenvalues();
    NodeVector f_nodes(nodes_);
    for (int k = 0; k < nodes_; ++k) f_nodes[k] = f0[representative[k]];
    const NodeVector a = eigen.eigenvectors().transpose() * root_area.cwiseProduct(f_nodes);
    spread_ = root_area.cwiseInverse().asDiagonal() * eigen.eigenvectors() * a.asDiagonal();
    roots_ = root_nodes * spread_;
    g0_ = g0;
    // As CVODE at a restart: a function not positive where the mode begins is
    // not watched (the level roots carry an offset so that an empty tank's is)
    watched_ = (g0.array() > 0.0).cast<double>();
    return true;
  }

  // Whether a watched root function is <= 0 at t (the values into *values if given).
  bool Crossed(double t, RootVector* values = nullptr) const {
    const RootVector g = Roots(t);
    if (values != nullptr) *values = g;
    return ((g.array() <= 0.0).cast<double>() * watched_.array()).any();
  }

  bool Watched(int slot) const { return watched_[slot] != 0.0; }

  Vec6 Levels(double t) const {
    const NodeVector moved = spread_ * Psi(t);
    Vec6 x = x0_ + rate_ * t;
    for (int i = 0; i < kTanks; ++i)
      if (node_of_[i] >= 0) x[i] += moved[node_of_[i]];
    return x;
  }

  RootVector Roots(double t) const { return g0_ + linear_ * t + roots_ * Psi(t); }

 private:
  NodeVector Psi(double t) const {
    NodeVector out(nodes_);
    for (int k = 0; k < nodes_; ++k) out[k] = ftc::Psi(lambda_[k], t);
    return out;
  }

  Vec6 x0_;
  int nodes_ = 0;
  std::array<int, kTanks> node_of_{};
  Vec6 rate_;
  NodeVector lambda_;
  NodeMatrix spread_;  // node displacement per psi
  RootVector g0_, linear_, watched_;
  RootMatrix roots_;
};

}  // namespace

LinearStepResult LinearConduitStep(const Vec6& x0, const Valves& u, const PlantParams& p,
                                   double dt, int max_events) {
  LinearStepResult r;
  r.x = x0;
  Clamp(&r.x, p);
  ModeSolution solution;
  while (r.t < dt) {
    const Mode mode = ComputeMode(r.x, u, p);
    if (!solution.Build(r.x, u, p, mode)) return r;  // the caller integrates the rest
    const double remaining = dt - r.t;
    // The first grid interval in which a root function falls to <= 0.
    double lo = 0, hi = remaining;
    bool found = false;
    for (int k = 1; k <= kGrid && !found; ++k) {
      const double t = remaining * k / kGrid;
      if (solution.Crossed(t)) {
        hi = t;
        found = true;
      } else {
        lo = t;
      }
    }
    if (!found) {
      r.x = solution.Levels(remaining);
      r.t = dt;
      break;
    }
    // Bisect to the earliest crossing: g > 0 at lo for every root, <= 0 at hi for one.
    while (hi - lo > kRootWidth * std::max(1.0, hi)) {
      const double mid = 0.5 * (lo + hi);
      if (solution.Crossed(mid)) {
        hi = mid;
      } else {
        lo = mid;
      }
    }
    RootVector g;
    solution.Crossed(hi, &g);
    r.x = solution.Levels(hi);
    for (int i = 0; i < kTanks; ++i)
      if (solution.Watched(i) && g[i] <= 0.0) r.x[i] = 0.0;  // located at its bottom: empty
    Clamp(&r.x, p);
    r.t = hi >= remaining ? dt : r.t + hi;
    if (++r.events > max_events) {
      throw std::runtime_error("LinearConduitStep: more than " + std::to_string(max_events) +
                               " mode switches in one step (chattering)");
    }
  }
  Clamp(&r.x, p);
  return r;
}

}  // namespace ftc
