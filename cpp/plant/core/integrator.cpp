// One control step of the hybrid tank dynamics with SUNDIALS CVODE (6.4).
//
// Equations. The ODE state is y = (x, S, D) in R^14:
//   dx/dt = f_mode(x)          levels, m (dynamics.cpp; affine in x per mode)
//   dS/dt = s_mode(x)          fuel pumped from each tank, m^3
//   dD/dt = deficit_mode(x)    unmet demand of each engine, m^3
// S and D ride along as quadratures: the supply is constant per mode except
// downstream of a pinned empty tank, where it follows the conduit inflow, so
// integrating it with the same method keeps the linear invariant
// sum_i c_i x_i + sum_i S_i = const (a linear multistep method preserves
// linear invariants exactly), which is the fuel balance the tests check.
//
// Solver. CV_ADAMS with fixed-point iteration, no linear solver: the field is
// non-stiff (the fastest time constant is c R / (k g) with at most k = 6
// tanks on the conduit, i.e. >= 1.7 s against steps of at most 1 s), so BDF's
// Newton iteration would only add Jacobian work. Each mode switch is a root
// (CVodeRootInit, kNumRoots functions, all crossing downwards); at a root the
// mode is recomputed and CVODE re-initialised there, so no step ever straddles
// a discontinuity of the right-hand side.
//
// Tolerances (IntegratorOptions): rtol = 1e-8, atol = 1e-10 m. Consumers need
// levels to 1e-4 m over whole episodes (the Python reference comparison) and
// to 1e-7 m for one step from a common state (test_physics_vs_reference.py);
// the terminal test's 1e-6 m^3 margin rests on conservation (exact up to
// rounding, see above), not on accuracy. Measured against rtol 1e-12 over
// 20000 random steps: worst level error 2.5e-8 m per step. rtol 1e-7 gives
// 3e-7 m (too close to 1e-7) at 0.8x the cost; 1e-10 gives 3e-10 m at 1.4x.

// Warm continuation. A step that starts exactly where the previous one ended,
// with the same valves and parameters, continues the integration without
// CVodeReInit: CVODE keeps its order and step size and needs 1-2 internal
// steps per second instead of ~12 from a cold start. Results then depend on
// the call history at the level of the tolerances, not more.
//
// Performance note: Debian's libsundials 6.4.1 is compiled without
// optimisation (-O0; see the disassembly of N_VWSqrSumLocal_Serial), so
// ~85% of a step is spent inside CVODE and its serial vector.
#include "plant/core/integrator.h"

#include <cvode/cvode.h>
#include <nvector/nvector_serial.h>
#include <sundials/sundials_context.h>
#include <sunnonlinsol/sunnonlinsol_fixedpoint.h>

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>
#include <type_traits>

namespace ftc {
namespace {

constexpr int kStateSize = 2 * kTanks + kEngines;  // x, S, D
constexpr int kSupplyOffset = kTanks;
constexpr int kDeficitOffset = 2 * kTanks;
// What the callbacks see: the problem of the current segment.
struct ProblemData {
  PlantParams params;
  Valves valves = Valves::Zero();
  Mode mode;
};

Vec6 Levels(N_Vector y) {
  return Eigen::Map<const Vec6>(N_VGetArrayPointer(y));
}

int Rhs(realtype /*t*/, N_Vector y, N_Vector ydot, void* user_data) noexcept {
  const auto* data = static_cast<const ProblemData*>(user_data);
  const realtype* in = N_VGetArrayPointer(y);
  realtype* out = N_VGetArrayPointer(ydot);
  for (int k = 0; k < kStateSize; ++k)
    if (!std::isfinite(in[k])) return 1;  // recoverable: CVODE retries with a smaller step
  Vec6 dx;
  Flows flows;
  EvaluateField(Eigen::Map<const Vec6>(in), data->params, data->mode, &dx, &flows);
  for (int i = 0; i < kTanks; ++i) {
    out[i] = dx[i];
    out[kSupplyOffset + i] = flows.supply[i];
  }
  for (int j = 0; j < kEngines; ++j) out[kDeficitOffset + j] = flows.deficit[j];
  return 0;
}

int Roots(realtype /*t*/, N_Vector y, realtype* gout, void* user_data) noexcept {
  const auto* data = static_cast<const ProblemData*>(user_data);
  const auto r = RootFunctions(Levels(y), data->valves, data->params, data->mode);
  std::copy(r.begin(), r.end(), gout);
  return 0;
}

// Owners of the SUNDIALS handles: each is freed by its own deleter, so a
// checked call failing halfway through Impl's constructor leaks nothing.
struct ContextFree {
  void operator()(SUNContext c) const { SUNContext_Free(&c); }
};
struct VectorDestroy {
  void operator()(N_Vector v) const { N_VDestroy(v); }
};
struct NonlinearSolverFree {
  void operator()(SUNNonlinearSolver s) const { SUNNonlinSolFree(s); }
};
struct CvodeFree {
  void operator()(void* mem) const { CVodeFree(&mem); }
};
using ContextPtr = std::unique_ptr<std::remove_pointer_t<SUNContext>, ContextFree>;
using VectorPtr = std::unique_ptr<std::remove_pointer_t<N_Vector>, VectorDestroy>;
using NonlinearSolverPtr =
    std::unique_ptr<std::remove_pointer_t<SUNNonlinearSolver>, NonlinearSolverFree>;
using CvodePtr = std::unique_ptr<void, CvodeFree>;

template <typename Ptr>
Ptr NonNull(Ptr p, const char* function) {
  if (p == nullptr) throw std::runtime_error(std::string(function) + " returned null");
  return p;
}

}  // namespace

struct StepIntegrator::Impl {
  IntegratorOptions options;
  // Declaration order is teardown order reversed: CVODE's memory goes first,
  // the context that all of them were created in last.
  ContextPtr context;
  VectorPtr y;
  NonlinearSolverPtr solver;
  CvodePtr cvode;
  ProblemData data;
  bool warm = false;  // CVODE's state continues the last step (see Step)
  realtype t = 0;     // CVODE's time at the end of the last step
  std::string last_error;  // message of CVODE's error handler, for the exception

  explicit Impl(const IntegratorOptions& o) : options(o) {
    SUNContext raw_context = nullptr;
    Check(SUNContext_Create(nullptr, &raw_context), "SUNContext_Create");
    context.reset(raw_context);
    y.reset(NonNull(N_VNew_Serial(kStateSize, context.get()), "N_VNew_Serial"));
    N_VConst(0.0, y.get());
    cvode.reset(NonNull(CVodeCreate(CV_ADAMS, context.get()), "CVodeCreate"));
    void* mem = cvode.get();
    Check(CVodeSetErrHandlerFn(mem, &Impl::ErrorHandler, this), "CVodeSetErrHandlerFn");
    Check(CVodeInit(mem, Rhs, 0.0, y.get()), "CVodeInit");
    Check(CVodeSStolerances(mem, options.rtol, options.atol), "CVodeSStolerances");
    Check(CVodeSetUserData(mem, &data), "CVodeSetUserData");
    solver.reset(
        NonNull(SUNNonlinSol_FixedPoint(y.get(), 0, context.get()), "SUNNonlinSol_FixedPoint"));
    Check(CVodeSetNonlinearSolver(mem, solver.get()), "CVodeSetNonlinearSolver");
    Check(CVodeRootInit(mem, kNumRoots, Roots), "CVodeRootInit");
    int directions[kNumRoots];
    std::fill(directions, directions + kNumRoots, -1);  // every root function falls to 0
    Check(CVodeSetRootDirection(mem, directions), "CVodeSetRootDirection");
    // Functions resting at exactly 0 at a restart (a tank just emptied) are expected.
    Check(CVodeSetNoInactiveRootWarn(mem), "CVodeSetNoInactiveRootWarn");
    Check(CVodeSetMaxNumSteps(mem, 5000), "CVodeSetMaxNumSteps");
  }

  Impl(const Impl&) = delete;
  Impl& operator=(const Impl&) = delete;

  static void ErrorHandler(int /*code*/, const char* module, const char* function, char* msg,
                           void* user_data) {
    auto* self = static_cast<Impl*>(user_data);
    self->last_error = std::string(module) + "::" + function + ": " + msg;
  }

  void Check(int flag, const char* function) {
    if (flag >= 0) return;
    std::string what = std::string(function) + " failed with code " + std::to_string(flag);
    if (!last_error.empty()) what += " (" + last_error + ")";
    last_error.clear();
    throw std::runtime_error(what);
  }
};

StepIntegrator::StepIntegrator(const IntegratorOptions& options)
    : impl_(std::make_unique<Impl>(options)) {}

StepIntegrator::~StepIntegrator() = default;

StepResult StepIntegrator::Step(const Vec6& x0, const Valves& u, const PlantParams& p,
                                double dt) {
  if (!(dt > 0)) throw std::invalid_argument("StepIntegrator::Step: dt must be > 0");
  Impl& m = *impl_;
  realtype* y = N_VGetArrayPointer(m.y.get());
  // Levels within kEmptySnap of the bottom are empty (params.h): a pump
  // switching on and off over 1e-16 m would only feed CVODE noise.
  const auto clamp_levels = [&]() { return ClampLevels(y, p.height); };

  // A step that starts exactly where the previous one ended, under the same
  // valves and parameters, continues the integration: the field is the same
  // and CVODE keeps its step size and order instead of restarting at order 1.
  const bool warm = m.warm && u == m.data.valves && SameParams(p, m.data.params) &&
                    x0 == Levels(m.y.get());
  realtype t = m.t;
  m.warm = false;  // until this step has succeeded
  if (!warm) {
    N_VConst(0.0, m.y.get());
    for (int i = 0; i < kTanks; ++i) y[i] = x0[i];
    clamp_levels();
    m.data.params = p;
    m.data.valves = u;
    t = 0;
  }
  // Supplied and deficit volumes accumulate along a warm run; this step's are
  // the increments.
  Vec6 supplied0;
  for (int i = 0; i < kTanks; ++i) supplied0[i] = y[kSupplyOffset + i];
  Vec2 deficit0;
  for (int j = 0; j < kEngines; ++j) deficit0[j] = y[kDeficitOffset + j];

  const realtype t_end = t + dt;
  StepResult result;
  bool restart = !warm;
  for (;;) {
    if (restart) {
      m.data.mode = ComputeMode(Levels(m.y.get()), u, p);
      m.Check(CVodeReInit(m.cvode.get(), t, m.y.get()), "CVodeReInit");
      restart = false;
    }
    m.Check(CVodeSetStopTime(m.cvode.get(), t_end), "CVodeSetStopTime");
    const int flag = CVode(m.cvode.get(), t_end, m.y.get(), &t, CV_NORMAL);
    m.Check(flag, "CVode");
    if (flag != CV_ROOT_RETURN) break;  // CV_TSTOP_RETURN or CV_SUCCESS: at t_end
    if (++result.events > m.options.max_events) {
      throw std::runtime_error("StepIntegrator::Step: more than " +
                               std::to_string(m.options.max_events) +
                               " mode switches in one step (chattering)");
    }
    int found[kNumRoots];
    m.Check(CVodeGetRootInfo(m.cvode.get(), found), "CVodeGetRootInfo");
    // A tank located at its bottom is empty: make it exactly so, and let the
    // new mode see it that way.
    for (int i = 0; i < kTanks; ++i)
      if (found[i] != 0) y[i] = 0.0;
    clamp_levels();
    restart = true;
    if (t >= t_end) break;  // a root at the very end: the next step restarts
  }
  // The next step may continue from here only if CVODE's state is exactly
  // the levels handed out (no clamp moved them) and the step did not end on
  // a root (whose new mode was never started).
  const bool ended_on_root = restart;
  m.warm = !clamp_levels() && !ended_on_root;
  m.t = t;
  for (int i = 0; i < kTanks; ++i) {
    result.x[i] = y[i];
    result.supplied[i] = y[kSupplyOffset + i] - supplied0[i];
  }
  for (int j = 0; j < kEngines; ++j)
    result.deficit[j] = std::max(0.0, y[kDeficitOffset + j] - deficit0[j]);
  return result;
}

}  // namespace ftc
