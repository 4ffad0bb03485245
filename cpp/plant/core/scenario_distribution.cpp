// Drawing fault scenarios from a declared distribution (scenario_distribution.h).
#include "plant/core/scenario_distribution.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>

namespace ftc {
namespace {

constexpr double kMinFactor = 1e-3;  // as the scenario files (scenario.h)

[[noreturn]] void Refuse(const std::string& what) {
  throw std::invalid_argument("ScenarioDistribution: " + what);
}

std::string Text(double v) {
  std::ostringstream os;
  os << v;
  return os.str();
}

void CheckProbability(const char* name, double p) {
  if (!(p >= 0.0 && p <= 1.0)) Refuse(std::string(name) + " must be in [0, 1], got " + Text(p));
}

void CheckRange(const char* name, const ScenarioDistribution::Range& r, double minimum) {
  if (!std::isfinite(r.first) || !std::isfinite(r.second) || r.first > r.second)
    Refuse(std::string(name) + " must be a finite [low, high] with low <= high, got [" +
           Text(r.first) + ", " + Text(r.second) + "]");
  if (r.first < minimum)
    Refuse(std::string(name) + " must be >= " + Text(minimum) + ", got [" + Text(r.first) +
           ", " + Text(r.second) + "]");
}

bool InRange(double v, const ScenarioDistribution::Range& r) {
  return v >= r.first && v <= r.second;
}

void CheckFactor(const std::string& key, double v, double probability,
                 const ScenarioDistribution::Range& r) {
  if (std::isinf(v) && v > 0) return;  // healthy
  if (probability > 0 && InRange(v, r)) return;
  Refuse("scenario " + key + " = " + Text(v) + " is outside the declared range [" +
         Text(r.first) + ", " + Text(r.second) + "]" +
         (probability > 0 ? "" : " (drawn with probability 0)"));
}

}  // namespace

void ScenarioDistribution::Validate() const {
  if (steps_per_interval <= 0)
    Refuse("steps_per_interval must be > 0, got " + std::to_string(steps_per_interval));
  if (life_intervals < 1)
    Refuse("life_intervals must be >= 1, got " + std::to_string(life_intervals));
  CheckProbability("tank_probability", tank_probability);
  CheckProbability("engine_probability", engine_probability);
  CheckProbability("dead_pump_probability", dead_pump_probability);
  CheckProbability("event_probability", event_probability);
  CheckProbability("stuck_valve_probability", stuck_valve_probability);
  CheckProbability("noise_probability", noise_probability);
  CheckRange("tank_factor", tank_factor, kMinFactor);
  CheckRange("engine_factor", engine_factor, kMinFactor);
  CheckRange("event_factor", event_factor, kMinFactor);
  CheckRange("noise_std", noise_std, 0.0);
  if (dead_pump_probability > 0 && life_intervals < 2)
    Refuse("dead_pump_probability > 0 needs life_intervals >= 2 (a pump dies after interval 0)");
}

void ScenarioDistribution::Check(const FaultScenario& s) const {
  if (s.mode != mode) Refuse("scenario '" + s.name + "' has another degradation mode");
  if (s.steps_per_interval != steps_per_interval)
    Refuse("scenario '" + s.name + "' steps_per_interval = " +
           std::to_string(s.steps_per_interval) + ", declared " +
           std::to_string(steps_per_interval));
  for (int i = 0; i < kTanks; ++i)
    CheckFactor("tank_factor[" + std::to_string(i) + "]", s.tank_factor[i], tank_probability,
                tank_factor);
  for (int j = 0; j < kEngines; ++j)
    CheckFactor("engine_factor[" + std::to_string(j) + "]", s.engine_factor[j],
                engine_probability, engine_factor);
  if (s.noise_std != 0.0 && !(noise_probability > 0 && InRange(s.noise_std, noise_std)))
    Refuse("scenario noise_std = " + Text(s.noise_std) + " is outside the declared range [" +
           Text(noise_std.first) + ", " + Text(noise_std.second) + "]");
  const std::int64_t life = static_cast<std::int64_t>(life_intervals) * steps_per_interval;
  for (std::size_t k = 0; k < s.events.size(); ++k) {
    const FaultEvent& e = s.events[k];
    const std::string key = "event[" + std::to_string(k + 1) + "]";
    if (e.at_step < 0 || e.at_step >= life)
      Refuse("scenario " + key + ".at_step = " + std::to_string(e.at_step) +
             " is outside the declared life [0, " + std::to_string(life) + ")");
    if (e.kind == FaultEvent::Kind::kStuckValve) {
      if (!(stuck_valve_probability > 0)) Refuse("scenario " + key + ": no stuck valves declared");
      continue;
    }
    const bool dead = e.kind == FaultEvent::Kind::kTank && e.factor == kDeadFactor &&
                      dead_pump_probability > 0;
    if (!dead && !(event_probability > 0 && InRange(e.factor, event_factor)))
      Refuse("scenario " + key + ".factor = " + Text(e.factor) +
             " is outside the declared range [" + Text(event_factor.first) + ", " +
             Text(event_factor.second) + "]");
  }
}

FaultScenario ScenarioDistribution::Draw(std::mt19937_64& rng) const {
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  const auto uniform = [&](const Range& r) { return r.first + (r.second - r.first) * unit(rng); };
  const auto index = [&](int n) { return static_cast<int>(rng() % static_cast<std::uint64_t>(n)); };
  const std::int64_t life = static_cast<std::int64_t>(life_intervals) * steps_per_interval;
  const auto step_in = [&](std::int64_t lo, std::int64_t hi) {
    return lo + static_cast<std::int64_t>(rng() % static_cast<std::uint64_t>(hi - lo));
  };
  FaultScenario s;
  s.name = "drawn";
  s.mode = mode;
  s.steps_per_interval = steps_per_interval;
  for (int i = 0; i < kTanks; ++i)
    if (unit(rng) < tank_probability) s.tank_factor[i] = uniform(tank_factor);
  for (int j = 0; j < kEngines; ++j)
    if (unit(rng) < engine_probability) s.engine_factor[j] = uniform(engine_factor);
  if (unit(rng) < dead_pump_probability) {
    FaultEvent e;
    e.kind = FaultEvent::Kind::kTank;
    e.index = index(kTanks);
    e.factor = kDeadFactor;
    e.at_step = step_in(steps_per_interval, life);
    s.events.push_back(e);
  }
  if (unit(rng) < event_probability) {
    FaultEvent e;
    const int component = index(kTanks + kEngines);
    e.kind = component < kTanks ? FaultEvent::Kind::kTank : FaultEvent::Kind::kEngine;
    e.index = component < kTanks ? component : component - kTanks;
    e.factor = uniform(event_factor);
    e.at_step = step_in(0, life);
    s.events.push_back(e);
  }
  if (unit(rng) < stuck_valve_probability) {
    FaultEvent e;
    e.kind = FaultEvent::Kind::kStuckValve;
    e.index = index(kTanks);
    e.state = static_cast<int>(rng() & 1);
    e.at_step = step_in(0, life);
    s.events.push_back(e);
  }
  if (unit(rng) < noise_probability) s.noise_std = uniform(noise_std);
  // sorted by at_step, stable (FaultScenario's contract)
  std::stable_sort(s.events.begin(), s.events.end(),
                   [](const FaultEvent& a, const FaultEvent& b) { return a.at_step < b.at_step; });
  return s;
}

std::vector<FaultScenario> DrawScenarios(const ScenarioDistribution& d, int count,
                                         std::uint64_t seed) {
  d.Validate();
  if (count < 0) Refuse("count must be >= 0, got " + std::to_string(count));
  std::vector<FaultScenario> out;
  out.reserve(static_cast<std::size_t>(count));
  for (int n = 0; n < count; ++n) {
    std::mt19937_64 rng(MixSeed(seed, static_cast<std::uint64_t>(n)));
    out.push_back(d.Draw(rng));
  }
  return out;
}

std::uint64_t MixSeed(std::uint64_t base, std::uint64_t stream) {
  std::uint64_t z = base + 0x9e3779b97f4a7c15ULL * (stream + 1);
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ULL;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebULL;
  return z ^ (z >> 31);
}

}  // namespace ftc
