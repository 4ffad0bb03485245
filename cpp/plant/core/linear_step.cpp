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
#include <cstdint>
#include <cstring>
#include <stdexcept>
#include <string>
#include <vector>

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

// What does not depend on the levels within a mode: the nodes, M's
// eigenvectors, the root functions' gradients along the nodes and along the
// tanks off the conduit. A function of the mode, the valves, the root slots in
// force and the parameters alone (evaluated at the levels 0, the same point
// for every mode), so an entry made by one plant serves any other.
struct Prepared {
  bool ok = false;  // false: the mode is not handled in closed form
  int nodes = 0;
  std::array<int, kTanks> node_of{};
  int representative[kTanks] = {};
  double lambda[kTanks] = {};
  // M = V diag(lambda) W (W = V^-1): vectors V, inverse W, node by node
  double vectors[kTanks][kTanks] = {};
  double inverse[kTanks][kTanks] = {};
  // the root functions' gradients along the eigenvectors (gradient along the
  // nodes times V) and along the tanks off the conduit
  double root_modes[kNumRoots][kTanks] = {};
  double root_off[kNumRoots][kTanks] = {};
  // psi at the grid's times over a whole control step (1 s): (g + 1) / kGrid
  double psi_grid[kGrid][kTanks] = {};
  // the root functions with a gradient (the others are constant within the mode)
  int live[kNumRoots] = {};
  int live_count = 0;
};

// The mode, valves and root slots as one key (params beside it).
std::uint64_t ModeKey(const Valves& u, const Mode& mode, std::uint32_t active) {
  std::uint64_t k = 0;
  for (int i = 0; i < kTanks; ++i) {
    k |= static_cast<std::uint64_t>(u[i] != 0) << i;
    k |= static_cast<std::uint64_t>(mode.source[i]) << (6 + i);
    k |= static_cast<std::uint64_t>(mode.sink[i]) << (12 + i);
    k |= static_cast<std::uint64_t>(mode.pinned[i]) << (18 + i);
    k |= static_cast<std::uint64_t>(mode.pumping[i]) << (24 + i);
    k |= static_cast<std::uint64_t>(mode.left[i]) << (30 + kNumRoots + i);  // after active
  }
  return k | static_cast<std::uint64_t>(active) << 30;
}

// Combines a hash with a value (splitmix64's finalizer over their sum, so
// every bit of either moves the low bits that index the cache).
std::uint64_t Mix(std::uint64_t h, std::uint64_t v) {
  std::uint64_t z = h + 0x9e3779b97f4a7c15ULL * (v + 1);
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
  return z ^ (z >> 31);
}

std::uint64_t HashParams(const PlantParams& p) {
  std::uint64_t h = 0;
  auto add = [&](double v) {
    std::uint64_t bits;
    std::memcpy(&bits, &v, sizeof bits);
    h = Mix(h, bits);
  };
  add(p.g);
  for (int i = 0; i < kTanks; ++i) {
    add(p.height[i]);
    add(p.area[i]);
    add(p.resistance[i]);
    add(p.pump[i]);
  }
  for (int j = 0; j < kEngines; ++j) add(p.demand[j]);
  return h;
}

bool Prepare(const Valves& u, const PlantParams& p, const Mode& mode, std::uint32_t active,
             Prepared* out);

// Prepared modes of this thread, in sets of two by (key, parameters) (the
// older of a set is replaced): plants that share parameters (a pool of one
// scenario, at the same age) share entries. An entry is a pure function of
// what it is keyed by, so which plant made it, and whether it was evicted
// meanwhile, changes no result.
class PreparedCache {
 public:
  const Prepared& Get(const Valves& u, const PlantParams& p, std::uint64_t params_hash,
                      const Mode& mode, std::uint32_t active) {
    const std::uint64_t key = ModeKey(u, mode, active);
    Slot* set = &slots_[2 * (Mix(params_hash, key) & (kSets - 1))];
    for (int w = 0; w < 2; ++w) {
      Slot& slot = set[w];
      if (slot.filled && slot.key == key && SameParams(slot.params, p)) {
        slot.used = ++clock_;
        return slot.prepared;
      }
    }
    Slot& slot = set[0].used <= set[1].used ? set[0] : set[1];
    slot.filled = false;
    slot.prepared.ok = Prepare(u, p, mode, active, &slot.prepared);
    slot.key = key;
    slot.params = p;
    slot.used = ++clock_;
    slot.filled = true;
    return slot.prepared;
  }

 private:
  // 4,096 entries of ~2.3 kB: ~9 MB a thread that steps plants in closed form
  // (a pool of the single fault with random valves meets ~1,200 modes an age)
  static constexpr std::size_t kSets = 2048;
  struct Slot {
    bool filled = false;
    std::uint64_t key = 0, used = 0;
    PlantParams params;
    Prepared prepared;
  };
  std::uint64_t clock_ = 0;
  std::vector<Slot> slots_ = std::vector<Slot>(2 * kSets);
};

PreparedCache& ThreadCache() {
  thread_local PreparedCache cache;
  return cache;
}

// M = V diag(lambda) V^-1 with real lambda. Usually M = C^-1 L (a star of
// conductances): C^1/2 M C^-1/2 is symmetric, and its eigenvectors give V
// at once. With a driven tank (Prepare) M is not of that kind: a general
// eigendecomposition, accepted if its eigenvalues are real and V is well
// conditioned (else CVODE integrates the mode).
struct Eigenbasis {
  NodeVector lambda;
  NodeMatrix vectors, inverse;
};

bool Decompose(const NodeMatrix& m, const NodeVector& area, int nodes, Eigenbasis* out) {
  const NodeVector root_area = area.cwiseSqrt();
  NodeMatrix s(nodes, nodes);
  double largest = 0, asymmetry = 0;
  for (int i = 0; i < nodes; ++i)
    for (int j = 0; j < nodes; ++j) {
      s(i, j) = root_area[i] * m(i, j) / root_area[j];
      largest = std::max(largest, std::abs(s(i, j)));
    }
  for (int i = 0; i < nodes; ++i)
    for (int j = 0; j < i; ++j) {
      asymmetry = std::max(asymmetry, std::abs(s(i, j) - s(j, i)));
      s(i, j) = s(j, i) = 0.5 * (s(i, j) + s(j, i));
    }
  if (asymmetry <= 1e-12 * largest) {
    const Eigen::SelfAdjointEigenSolver<NodeMatrix> eigen(s);
    if (eigen.info() != Eigen::Success) return false;
    out->lambda = eigen.eigenvalues();
    out->vectors = root_area.cwiseInverse().asDiagonal() * eigen.eigenvectors();
    out->inverse = eigen.eigenvectors().transpose() * root_area.asDiagonal();
    return true;
  }
  const Eigen::EigenSolver<NodeMatrix> eigen(m);
  if (eigen.info() != Eigen::Success) return false;
  const double scale = std::max(m.cwiseAbs().maxCoeff(), 1e-300);
  if (eigen.eigenvalues().imag().cwiseAbs().maxCoeff() > 1e-12 * scale) return false;
  out->lambda = eigen.eigenvalues().real();
  out->vectors = eigen.eigenvectors().real();
  const Eigen::FullPivLU<NodeMatrix> lu(out->vectors);
  if (!lu.isInvertible() || lu.rcond() < 1e-8) return false;  // nearly defective
  out->inverse = lu.inverse();
  // LU's estimate can miss a defective basis: two driven tanks give M the
  // eigenvalue 0 twice, and where M has it exactly the solver may return one
  // eigenvector for both (found on the suite's random-01 with the preparation
  // at the levels 0: 6e-3 m from CVODE in a step). V W must be the identity.
  const NodeMatrix identity = NodeMatrix::Identity(nodes, nodes);
  if ((out->vectors * out->inverse - identity).cwiseAbs().maxCoeff() > 1e-9) return false;
  return true;
}

// The nodes, M, its eigenvectors and the root functions' gradients, read off
// the field and the root functions (slots `active`) at the levels 0 and one
// metre along each node's direction: each is affine within the mode, so the
// differences are exact up to rounding, wherever they are taken.
bool Prepare(const Valves& u, const PlantParams& p, const Mode& mode, std::uint32_t active,
             Prepared* out) {
  int nodes = 0;
  out->node_of.fill(-1);
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
      out->node_of[i] = 0;
      group_area += p.area[i];
      if (nodes == 0) out->representative[nodes++] = i;
    }
  }
  if (nodes == 0) return false;  // no conduit
  area[0] = group_area;
  for (int i = 0; i < kTanks; ++i) {
    if (mode.sink[i] && !mode.pinned[i]) {  // a pinned tank stays at 0: no node
      out->node_of[i] = nodes;
      area[nodes] = p.area[i];
      out->representative[nodes++] = i;
    }
  }
  const int conduit_nodes = nodes;

  // The field along each node's direction (sources together, each sink alone).
  const Vec6 origin = Vec6::Zero();
  const Vec6 f0 = Derivative(origin, u, p, mode);
  const RootVector g0 = AsVector(RootFunctionsOf(origin, p, mode, active));
  auto direction = [&](int d) {
    Vec6 moved = origin;
    for (int i = 0; i < kTanks; ++i)
      if (out->node_of[i] == d) moved[i] += 1.0;
    return moved;
  };
  Eigen::Matrix<double, kTanks, kTanks> df;
  for (int d = 0; d < conduit_nodes; ++d) df.col(d) = Derivative(direction(d), u, p, mode) - f0;
  // A tank off the conduit whose pump passes on what a pinned tank upstream does
  // not supply moves with the group: a node too (it does not act back).
  for (int i = 0; i < kTanks; ++i) {
    if (out->node_of[i] >= 0 || mode.pinned[i]) continue;
    if ((df.row(i).head(conduit_nodes).array() != 0.0).any()) {
      out->node_of[i] = nodes;
      area[nodes] = p.area[i];
      out->representative[nodes++] = i;
    }
  }
  out->nodes = nodes;
  area.conservativeResize(nodes);
  NodeMatrix m = NodeMatrix::Zero(nodes, nodes);
  RootMatrix root_nodes(kNumRoots, nodes);
  for (int d = 0; d < nodes; ++d) {
    const Vec6 moved = direction(d);
    if (d >= conduit_nodes) df.col(d) = Derivative(moved, u, p, mode) - f0;
    for (int k = 0; k < nodes; ++k) m(k, d) = df(out->representative[k], d);
    for (int i = 0; i < kTanks; ++i)
      if (out->node_of[i] < 0 && df(i, d) != 0.0) return false;  // not affine as assumed
    root_nodes.col(d) = AsVector(RootFunctionsOf(moved, p, mode, active)) - g0;
  }
  // Tanks off the conduit fall at their constant rate: a direction each (used
  // where the rate is not 0).
  for (int i = 0; i < kTanks; ++i) {
    for (int m = 0; m < kNumRoots; ++m) out->root_off[m][i] = 0.0;
    if (out->node_of[i] >= 0) continue;
    Vec6 moved = origin;
    moved[i] += 1.0;
    const RootVector column = AsVector(RootFunctionsOf(moved, p, mode, active)) - g0;
    for (int m = 0; m < kNumRoots; ++m) out->root_off[m][i] = column[m];
  }
  Eigenbasis basis;
  if (!Decompose(m, area, nodes, &basis)) return false;
  const RootMatrix root_modes = root_nodes * basis.vectors;
  for (int k = 0; k < nodes; ++k) {
    out->lambda[k] = basis.lambda[k];
    for (int j = 0; j < nodes; ++j) {
      out->vectors[k][j] = basis.vectors(k, j);
      out->inverse[k][j] = basis.inverse(k, j);
    }
    for (int m = 0; m < kNumRoots; ++m) out->root_modes[m][k] = root_modes(m, k);
  }
  out->live_count = 0;
  for (int m = 0; m < kNumRoots; ++m) {
    bool live = false;
    for (int k = 0; k < kTanks; ++k)
      live = live || out->root_off[m][k] != 0.0 || (k < nodes && out->root_modes[m][k] != 0.0);
    if (live) out->live[out->live_count++] = m;
  }
  for (int g = 0; g < kGrid; ++g) {
    const double t = static_cast<double>(g + 1) / kGrid;  // as Step's grid computes it for dt 1
    for (int k = 0; k < nodes; ++k) out->psi_grid[g][k] = Psi(out->lambda[k], t);
  }
  return true;
}

// One mode's closed form: x(t) = x0 + rate t + D V (a .* psi(t)), a = W f0
// on the nodes, where D spreads the conduit nodes back onto the tanks, and
// the root functions g(t) = g0 + L t + K psi(t), K = G V diag(a) (G: their
// gradients along the nodes).
class ModeSolution {
 public:
  // Prepares the mode at x (from `cache`, the calling thread's prepared modes).
  // Returns false where the mode is not handled (a pinned tank upstream of a
  // pump that cannot cover its engine's demand) or M has no real,
  // well-conditioned eigenbasis.
  bool Build(const Vec6& x, const Valves& u, const PlantParams& p, std::uint64_t params_hash,
             const Mode& mode, PreparedCache& cache) {
    psi_t_ = -1;  // the memo of Psi (below) is the last mode's
    Vec6 f0;
    std::array<double, kNumRoots> g0;
    std::uint32_t active = 0;
    FieldAndRoots(x, p, mode, &f0, &g0, &active);
    prep_ = &cache.Get(u, p, params_hash, mode, active);
    if (!prep_->ok) return false;
    Start(x, f0, g0);
    return true;
  }

  // Whether no root function can end the mode within [0, t] (checked on the
  // grid in Step): each term of g(t) = g0 + L t + sum_k K_k psi_k(t) is monotone
  // in t from 0 (psi_k' = e^{lambda_k t} > 0), so g lies between g0 plus the
  // negative and g0 plus the positive terms at t. A watched function bounded
  // above 0, or an unwatched one bounded below 0 (never armed), cannot be seen
  // crossing at any grid time; the margin covers the rounding of g's
  // evaluation (a few ulps of its terms' magnitude). Not finite: not proven.
  //
  // The functions not bounded so are kept (Open): only they can be seen
  // crossing at a grid time, and arming (Arm) leaves the others as they are
  // (one bounded above 0 is positive, so watched, at every grid time; one
  // bounded below 0 is never armed), so the grid evaluates only them.
  bool NoCrossingWithin(double t) {
    const double* psi = PsiAt(t);
    const int nodes = prep_->nodes;
    open_count_ = 0;
    for (int m = 0; m < kNumRoots; ++m) {  // a constant function: its value bounds it
      if (live_[m]) continue;
      const double margin = 1e-10 * std::abs(g0_[m]);
      if (!(g0_[m] > margin || (!watched_[m] && g0_[m] < -margin))) open_[open_count_++] = m;
    }
    for (int r = 0; r < prep_->live_count; ++r) {
      const int m = prep_->live[r];
      const double lin = linear_[m] * t;
      double low = g0_[m] + std::min(0.0, lin), high = g0_[m] + std::max(0.0, lin);
      double size = std::abs(g0_[m]) + std::abs(lin);
      for (int k = 0; k < nodes; ++k) {
        const double term = roots_[m][k] * psi[k];
        low += std::min(0.0, term);
        high += std::max(0.0, term);
        size += std::abs(term);
      }
      const double margin = 1e-10 * size;
      const bool above = low > margin;
      const bool below = !watched_[m] && high < -margin;
      if (!(above || below)) open_[open_count_++] = m;
    }
    return open_count_ == 0;
  }

  // Whether a watched function among those NoCrossingWithin left open is <= 0
  // at t; their values into *values (the others' entries: 1, as never crossed).
  bool OpenCrossed(double t, RootVector* values) const {
    const double* psi = PsiAt(t);
    values->setOnes();
    bool crossed = false;
    for (int r = 0; r < open_count_; ++r) {
      const int m = open_[r];
      const double g = RootWith(m, t, psi);
      (*values)[m] = g;
      crossed = crossed || (watched_[m] && g <= 0.0);
    }
    return crossed;
  }

  // Watches the open functions positive in g (values at a time before any
  // crossing): as CVODE reactivates a root function that was 0 (or below) at a
  // restart once it has moved above 0, a later downward crossing of it ends the
  // mode too.
  void ArmOpen(const RootVector& g) {
    for (int r = 0; r < open_count_; ++r) watched_[open_[r]] = g[open_[r]] > 0.0;
  }

  // Whether a watched root function is <= 0 at t (the values into *values if given).
  bool Crossed(double t, RootVector* values) const {
    *values = Roots(t);
    bool crossed = false;
    for (int m = 0; m < kNumRoots; ++m) crossed = crossed || (watched_[m] && (*values)[m] <= 0.0);
    return crossed;
  }

  bool Watched(int slot) const { return watched_[slot]; }

  Vec6 Levels(double t) const {
    const double* psi = PsiAt(t);
    const int nodes = prep_->nodes;
    double weighted[kTanks], moved[kTanks];
    for (int j = 0; j < nodes; ++j) weighted[j] = a_[j] * psi[j];
    for (int k = 0; k < nodes; ++k) {
      double sum = 0;
      for (int j = 0; j < nodes; ++j) sum += prep_->vectors[k][j] * weighted[j];
      moved[k] = sum;
    }
    Vec6 x;
    for (int i = 0; i < kTanks; ++i) {
      x[i] = x0_[i] + rate_[i] * t;
      if (prep_->node_of[i] >= 0) x[i] += moved[prep_->node_of[i]];
    }
    return x;
  }

  RootVector Roots(double t) const {
    const double* psi = PsiAt(t);
    RootVector g = Eigen::Map<const RootVector>(g0_);  // the constant ones
    for (int r = 0; r < prep_->live_count; ++r) g[prep_->live[r]] = RootWith(prep_->live[r], t, psi);
    return g;
  }

  // Root function m alone at t.
  double Root(int m, double t) const { return RootWith(m, t, PsiAt(t)); }

  // Root function m alone at t, and its slope there (psi_k' = e^{lambda_k t}).
  double RootAndSlope(int m, double t, double* slope) const {
    if (!live_[m]) {
      *slope = 0.0;
      return g0_[m];
    }
    double value = g0_[m] + linear_[m] * t, rate = linear_[m];
    for (int k = 0; k < prep_->nodes; ++k) {
      const double lambda = prep_->lambda[k];
      const double e = lambda == 0.0 ? 0.0 : std::expm1(lambda * t);
      value += roots_[m][k] * (lambda == 0.0 ? t : e / lambda);
      rate += roots_[m][k] * (e + 1.0);
    }
    *slope = rate;
    return value;
  }

  // The solution from x: f0 and g0 are the field and the root functions there.
  void Start(const Vec6& x, const Vec6& f0, const std::array<double, kNumRoots>& g0) {
    const Prepared& prep = *prep_;
    const int nodes = prep.nodes;
    for (int i = 0; i < kTanks; ++i) {
      x0_[i] = x[i];
      rate_[i] = prep.node_of[i] < 0 ? f0[i] : 0.0;
    }
    for (int k = 0; k < nodes; ++k) {
      double sum = 0;
      for (int j = 0; j < nodes; ++j) sum += prep.inverse[k][j] * f0[prep.representative[j]];
      a_[k] = sum;
    }
    for (int m = 0; m < kNumRoots; ++m) {
      g0_[m] = g0[m];
      linear_[m] = 0.0;
      live_[m] = false;
      watched_[m] = g0[m] > 0.0;
    }
    int moving[kTanks], moving_count = 0;  // the tanks off the conduit that move
    for (int i = 0; i < kTanks; ++i)
      if (rate_[i] != 0.0) moving[moving_count++] = i;
    for (int r = 0; r < prep.live_count; ++r) {
      const int m = prep.live[r];
      live_[m] = true;
      double lin = 0, sum = 0;
      for (int j = 0; j < moving_count; ++j) lin += prep.root_off[m][moving[j]] * rate_[moving[j]];
      linear_[m] = lin;
      for (int k = 0; k < nodes; ++k) {
        roots_[m][k] = prep.root_modes[m][k] * a_[k];
        sum += roots_[m][k];
      }
      // As CVODE at a restart: a function not positive where the mode begins
      // is not watched (the level roots carry an offset so that an empty
      // tank's is). A function exactly at 0 that rises at once is watched from
      // the start: CVODE's first internal step, a fraction of the grid's, sees
      // it above 0 and reactivates it, so its return to 0 is an event. (A
      // member that leaves a tie does not start so: its root is the leave
      // condition, positive where it leaves; dynamics.cpp.)
      if (g0[m] == 0.0 && lin + sum > 0.0) watched_[m] = true;
    }
  }

 private:
  double RootWith(int m, double t, const double* psi) const {
    if (!live_[m]) return g0_[m];
    double g = g0_[m] + linear_[m] * t;
    for (int k = 0; k < prep_->nodes; ++k) g += roots_[m][k] * psi[k];
    return g;
  }

  // psi(t): over a whole control step the grid's times from the preparation,
  // else kept for the last t asked (the root search's times recur: the
  // bracket's ends, the levels where the step stops)
  const double* PsiAt(double t) const {
    const double slot = t * kGrid;
    const int g = static_cast<int>(slot) - 1;
    if (g >= 0 && g < kGrid && slot == static_cast<double>(g + 1) &&
        static_cast<double>(g + 1) / kGrid == t)
      return prep_->psi_grid[g];
    if (t != psi_t_) {
      for (int k = 0; k < prep_->nodes; ++k) psi_[k] = ftc::Psi(prep_->lambda[k], t);
      psi_t_ = t;
    }
    return psi_;
  }

  const Prepared* prep_ = nullptr;
  // the solution from x0_
  double x0_[kTanks] = {}, rate_[kTanks] = {}, a_[kTanks] = {};
  double g0_[kNumRoots] = {}, linear_[kNumRoots] = {};
  bool watched_[kNumRoots] = {};
  bool live_[kNumRoots] = {};  // the function has a gradient (Prepared::live)
  int open_[kNumRoots] = {};   // the functions NoCrossingWithin did not bound
  int open_count_ = 0;
  double roots_[kNumRoots][kTanks] = {};
  mutable double psi_t_ = -1;  // the time psi_ is for (-1: none)
  mutable double psi_[kTanks] = {};
};

}  // namespace

// A plant's stepper keeps only its parameters' hash: the mode's solution is
// rebuilt at every segment (ModeSolution::Build), so it lives on the stack of
// Step, hot in the cache, and a pool of thousands of plants carries no copy of it.
struct LinearStepper::Impl {
  PlantParams params;  // the last step's, and their hash
  std::uint64_t params_hash = HashParams(PlantParams{});
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
  ModeSolution solution;
  PreparedCache& cache = ThreadCache();  // one thread-local look-up a step
  if (!SameParams(p, impl_->params)) {
    impl_->params = p;
    impl_->params_hash = HashParams(p);
  }
  while (r.t < dt) {
    const Mode mode = ComputeMode(r.x, u, p);
    // a mode not handled here: the caller integrates the rest
    if (!solution.Build(r.x, u, p, impl_->params_hash, mode, cache)) return r;
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
      if (solution.OpenCrossed(t, &g)) {
        hi = t;
        at_hi = g;
        found = true;
      } else {
        lo = t;
        at_lo = g;
        solution.ArmOpen(g);
      }
    }
    if (!found) {
      r.x = solution.Levels(remaining);
      r.t = dt;
      break;
    }
    // The earliest crossing in (lo, hi]: each watched function that is <= 0 at
    // hi is located to the bracket width by Newton's method kept inside the
    // bracket (a step out of it, or after 40 steps, halves the bracket; a step
    // shorter than the width probes the other side of the iterate, closing the
    // bracket there); the earliest wins.
    if (lo == 0) at_lo = solution.Roots(0);
    double first_lo = lo, first_hi = hi;
    for (int m = 0; m < kNumRoots; ++m) {
      if (!solution.Watched(m) || at_hi[m] > 0.0) continue;
      double a = lo, b = first_hi, fa = at_lo[m], fb = solution.Root(m, b);
      if (fb > 0.0) continue;  // crosses after the earliest found so far
      double c = (a * fb - b * fa) / (fb - fa);  // the secant's first guess
      for (int iteration = 0; b - a > kRootWidth * std::max(1.0, b); ++iteration) {
        if (!(c > a && c < b) || iteration >= 40) c = 0.5 * (a + b);
        double slope = 0;
        const double fc = solution.RootAndSlope(m, c, &slope);
        if (fc <= 0.0) {
          b = c;
          fb = fc;
        } else {
          a = c;
          fa = fc;
        }
        const double next = slope != 0.0 ? c - fc / slope : 0.5 * (a + b);
        const double close = 0.5 * kRootWidth * std::max(1.0, b);
        c = std::abs(next - c) >= close ? next : (fc <= 0.0 ? c - close : c + close);
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
