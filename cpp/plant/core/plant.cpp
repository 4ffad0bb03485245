// The plant as a discrete-time system (plant-model.md, "Episodes" and
// "Degradation"): episodes, termination, interval truncation, operating age,
// abrupt faults (parameter jumps, stuck valves) and sensor noise around the
// CVODE step.
#include "plant/core/plant.h"

#include <limits>

#include "plant/core/rollout.h"

namespace ftc {

namespace {
constexpr double kControlStep = 1.0;  // s of plant time per control step
constexpr double kTerminalMargin = 1e-6;  // m^3, in favour of ending (spec)
}  // namespace

Plant::Plant(const FaultScenario& scenario, std::uint64_t seed, const PlantParams& nominal,
             const IntegratorOptions& options, StepMethod method)
    : scenario_(scenario), nominal_(nominal), options_(options), method_(method), rng_(seed) {
  if (method_ == StepMethod::kCvode) integrator_ = std::make_unique<StepIntegrator>(options_);
  if (method_ == StepMethod::kClosedForm) linear_ = std::make_unique<LinearStepper>();
  if (scenario_.steps_per_interval <= 0)
    throw std::invalid_argument("Plant: steps_per_interval must be > 0");
  if (!(scenario_.noise_std >= 0)) throw std::invalid_argument("Plant: noise_std must be >= 0");
  // Before the first Reset the plant shows full tanks; the first Step (or
  // Reset) starts episode 0.
  last_.level = nominal_.height;
  last_.observed = nominal_.height;
  last_.episode = -1;  // no episode yet
}

Plant::~Plant() = default;
Plant::Plant(Plant&&) noexcept = default;
Plant& Plant::operator=(Plant&&) noexcept = default;

void Plant::Reset() { StartEpisode(false); }

void Plant::ResetEvaluation() {
  eval_step_ = operating_steps_ > 0 ? operating_steps_ - 1 : 0;
  StartEpisode(true);
}

void Plant::StartEpisode(bool evaluation) {
  Vec6 x = nominal_.height;
  if (scenario_.random_start) {
    std::uniform_real_distribution<double> fraction(0.8, 1.0);
    for (int i = 0; i < kTanks; ++i) x[i] = fraction(rng_) * nominal_.height[i];
  }
  last_ = StepOutcome{};
  last_.evaluation = evaluation;
  last_.level = x;
  last_.observed = Observe(x);
  last_.episode = episodes_started_++;
  last_.age = current_age();
}

const StepOutcome& Plant::Step(const Valves& u) {
  if (last_.episode < 0 || episode_over()) StartEpisode(last_.evaluation);
  const std::int64_t at = step_in_force();
  const double age = AgeAt(scenario_, at);
  const PlantParams& p = ParamsInForce(at);
  const Valves applied = StuckValvesAtStep(scenario_, at).Apply(u);
  const StepResult r = Integrate(last_.level, applied, p);

  last_.level = r.x;
  last_.observed = Observe(r.x);
  last_.valves = applied;
  last_.deficit = r.deficit;
  last_.age = age;
  ++last_.step;
  last_.terminal = IsTerminal(r.x, p, kControlStep);
  last_.truncated = false;
  if (!last_.evaluation) {
    ++operating_steps_;
    last_.truncated =
        !last_.terminal && operating_steps_ % scenario_.steps_per_interval == 0;
  }
  return last_;
}

const PlantParams& Plant::ParamsInForce(std::int64_t at) {
  // The parameters change only with the age and the factor events applied
  // (DegradedParamsAtStep): kept while both stay as they were.
  const double age = AgeAt(scenario_, at);
  int events = 0;
  for (const FaultEvent& e : scenario_.events) {
    if (e.at_step > at) break;  // sorted by at_step
    ++events;
  }
  if (!(params_valid_ && age == params_age_ && events == params_events_)) {
    params_ = ParamsAtStep(at);
    params_age_ = age;
    params_events_ = events;
    params_valid_ = true;
  }
  return params_;
}

StepIntegrator& Plant::Cvode() {
  if (!integrator_) integrator_ = std::make_unique<StepIntegrator>(options_);
  return *integrator_;
}

StepResult Plant::Integrate(const Vec6& x, const Valves& u, const PlantParams& p) {
  if (method_ == StepMethod::kCvode) return Cvode().Step(x, u, p, kControlStep);
  if ((u.array() != 0).count() < 2) return IdleConduitStep(x, u, p, kControlStep);
  const LinearStepResult linear = linear_->Step(x, u, p, kControlStep, options_.max_events);
  if (linear.t >= kControlStep) {
    StepResult r;
    r.x = linear.x;
    r.events = linear.events;
    r.supplied.setConstant(std::numeric_limits<double>::quiet_NaN());
    r.deficit.setConstant(std::numeric_limits<double>::quiet_NaN());
    return r;
  }
  // the rest of the step, from where the closed form stopped
  StepResult r = Cvode().Step(linear.x, u, p, kControlStep - linear.t);
  r.events += linear.events;
  r.supplied.setConstant(std::numeric_limits<double>::quiet_NaN());
  r.deficit.setConstant(std::numeric_limits<double>::quiet_NaN());
  return r;
}

bool Plant::IsTerminal(const Vec6& x, const PlantParams& p, double dt) {
  return p.area.dot(x) < p.demand.sum() * dt + kTerminalMargin;
}

Vec6 Plant::Observe(const Vec6& x) {
  if (scenario_.noise_std <= 0) return x;
  std::normal_distribution<double> noise(0.0, scenario_.noise_std);
  Vec6 y = x;
  for (int i = 0; i < kTanks; ++i) y[i] += noise(rng_);
  return y;
}

}  // namespace ftc
