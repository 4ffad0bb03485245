// A batch of plants stepped by one call (pool.h).
#include "plant/core/pool.h"

#include <algorithm>
#include <array>
#include <stdexcept>
#include <string>

#include "plant/core/reward.h"

namespace ftc {
namespace {

// Envs handed to a thread at a time: ~50-200 us of work in closed form, a few
// cache lines of output, and enough chunks to even out the slow envs.
constexpr int kChunk = 32;
// Streams of MixSeed for a renewed plant's seed and its scenario's draw.
constexpr std::uint64_t kScenarioStream = 0x5ce7a210ULL;

}  // namespace

// -- Workers --------------------------------------------------------------------
Workers::Workers(int threads) {
  if (threads < 1) throw std::invalid_argument("Workers: threads must be >= 1");
  for (int k = 1; k < threads; ++k) threads_.emplace_back([this] { Loop(); });
}

Workers::~Workers() {
  {
    std::lock_guard<std::mutex> lock(mutex_);
    stop_ = true;
  }
  wake_.notify_all();
  for (std::thread& t : threads_) t.join();
}

void Workers::Run(int n, const std::function<void(int)>& task) {
  if (threads_.empty() || n <= kChunk) {  // not worth waking anyone
    for (int i = 0; i < n; ++i) task(i);
    return;
  }
  {
    std::lock_guard<std::mutex> lock(mutex_);
    task_ = &task;
    n_ = n;
    next_.store(0);
    busy_ = static_cast<int>(threads_.size());
    error_ = nullptr;
    ++generation_;
  }
  wake_.notify_all();
  Drain();
  std::unique_lock<std::mutex> lock(mutex_);
  done_.wait(lock, [this] { return busy_ == 0; });
  task_ = nullptr;
  if (error_) {
    std::exception_ptr error = error_;
    error_ = nullptr;
    std::rethrow_exception(error);
  }
}

void Workers::Drain() {
  for (;;) {
    const int begin = next_.fetch_add(kChunk);
    if (begin >= n_) return;
    const int end = std::min(n_, begin + kChunk);
    for (int i = begin; i < end; ++i) {
      try {
        (*task_)(i);
      } catch (...) {
        std::lock_guard<std::mutex> lock(mutex_);
        if (!error_) error_ = std::current_exception();
      }
    }
  }
}

void Workers::Loop() {
  std::uint64_t seen = 0;
  for (;;) {
    {
      std::unique_lock<std::mutex> lock(mutex_);
      wake_.wait(lock, [&] { return stop_ || generation_ != seen; });
      if (stop_) return;
      seen = generation_;
    }
    Drain();
    std::lock_guard<std::mutex> lock(mutex_);
    if (--busy_ == 0) done_.notify_one();
  }
}

// -- PlantPool --------------------------------------------------------------------
namespace {

int ThreadCount(int requested) {
  if (requested < 0) throw std::invalid_argument("PlantPool: threads must be >= 0");
  if (requested > 0) return requested;
  return std::max(1, static_cast<int>(std::thread::hardware_concurrency()));
}

}  // namespace

PlantPool::PlantPool(const std::vector<FaultScenario>& scenarios,
                     const std::vector<std::uint64_t>& seeds, const PoolOptions& options,
                     const ScenarioDistribution* distribution)
    : options_(options), workers_(ThreadCount(options.threads)) {
  if (scenarios.empty()) throw std::invalid_argument("PlantPool: no envs (0 scenarios)");
  if (options_.life_intervals < 0)
    throw std::invalid_argument("PlantPool: life_intervals must be >= 0");
  if (distribution != nullptr) {
    distribution->Validate();
    distribution_ = std::make_unique<ScenarioDistribution>(*distribution);
  }
  Reseed(scenarios, seeds);
}

void PlantPool::Reseed(const std::vector<FaultScenario>& scenarios,
                       const std::vector<std::uint64_t>& seeds) {
  if (scenarios.size() != seeds.size() || (!envs_.empty() && scenarios.size() != envs_.size()))
    throw std::invalid_argument("PlantPool: " + std::to_string(scenarios.size()) +
                                " scenarios and " + std::to_string(seeds.size()) +
                                " seeds for " + std::to_string(envs_.size()) + " envs");
  std::vector<Env> envs;
  envs.reserve(scenarios.size());
  for (std::size_t i = 0; i < scenarios.size(); ++i)  // Plant checks each scenario
    envs.push_back(Env{Plant(scenarios[i], seeds[i], nominal_, {}, options_.method), seeds[i]});
  envs_ = std::move(envs);
}

void PlantPool::StartEpisode(int i) {
  Env& e = envs_[static_cast<std::size_t>(i)];
  const FaultScenario& s = e.plant.scenario();
  if (options_.life_intervals > 0 &&
      e.plant.operating_steps() >=
          static_cast<std::int64_t>(options_.life_intervals) * s.steps_per_interval) {
    ++e.life;
    FaultScenario next = s;
    if (distribution_) {
      std::mt19937_64 rng(MixSeed(e.seed ^ kScenarioStream, static_cast<std::uint64_t>(e.life)));
      next = distribution_->Draw(rng);
    }
    e.plant = Plant(next, MixSeed(e.seed, static_cast<std::uint64_t>(e.life)), nominal_, {},
                    options_.method);
  }
  e.plant.Reset();
  e.needs_reset = false;
}

void PlantPool::WriteState(int i, const PoolOutput& out) const {
  const StepOutcome& o = envs_[static_cast<std::size_t>(i)].plant.last();
  if (out.obs != nullptr)
    for (int k = 0; k < kTanks; ++k)
      out.obs[i * kTanks + k] = static_cast<float>(std::clamp(o.observed[k], 0.0, 1.0));
  if (out.age != nullptr) out.age[i] = o.age;
  if (out.episode_step != nullptr) out.episode_step[i] = o.step;
}

void PlantPool::WriteValves(int i, const Valves& applied, const PoolOutput& out) {
  if (out.valves == nullptr) return;
  for (int k = 0; k < kTanks; ++k)
    out.valves[i * kTanks + k] = static_cast<std::int8_t>(applied[k] != 0);
}

void PlantPool::Reset(const PoolOutput& out) {
  workers_.Run(size(), [&](int i) {
    StartEpisode(i);
    WriteState(i, out);
    WriteValves(i, Valves::Zero(), out);
    if (out.reward != nullptr) out.reward[i] = 0.0;
    if (out.terminated != nullptr) out.terminated[i] = false;
    if (out.truncated != nullptr) out.truncated[i] = false;
    if (out.final_mask != nullptr) out.final_mask[i] = false;
  });
}

void PlantPool::Step(const std::int8_t* actions, const PoolOutput& out) {
  // The envs in the order of their valves (a counting sort by the 6-bit mask):
  // envs with the same valves follow the same branches and prepared modes one
  // after the other, which the CPU predicts and caches (random valves in index
  // order mispredicted ~110 branches an env step). Each env's step depends on
  // that env alone and the prepared modes are pure functions of their keys
  // (linear_step.h), so the order changes no result.
  const int n = size();
  std::array<int, kValveMasks + 1> start{};
  masks_.resize(static_cast<std::size_t>(n));
  order_.resize(static_cast<std::size_t>(n));
  for (int i = 0; i < n; ++i) {
    int mask = 0;
    for (int k = 0; k < kTanks; ++k) mask |= (actions[i * kTanks + k] != 0) << k;
    masks_[static_cast<std::size_t>(i)] = static_cast<std::uint8_t>(mask);
    ++start[static_cast<std::size_t>(mask) + 1];
  }
  for (int m = 0; m < kValveMasks; ++m) start[m + 1] += start[m];
  for (int i = 0; i < n; ++i) order_[static_cast<std::size_t>(start[masks_[i]]++)] = i;
  workers_.Run(n, [&](int k) { StepOne(order_[static_cast<std::size_t>(k)], actions, out); });
}

void PlantPool::StepOne(int i, const std::int8_t* actions, const PoolOutput& out) {
  Env& e = envs_[static_cast<std::size_t>(i)];
  if (out.final_mask != nullptr) out.final_mask[i] = false;
  if (e.needs_reset) {  // kNextStep: this step is the reset
    StartEpisode(i);
    WriteState(i, out);
    WriteValves(i, Valves::Zero(), out);
    if (out.reward != nullptr) out.reward[i] = 0.0;
    if (out.terminated != nullptr) out.terminated[i] = false;
    if (out.truncated != nullptr) out.truncated[i] = false;
    if (out.cg != nullptr) {  // the terms of the reset state, no valves open
      const RewardTerms t = ComputeReward(e.plant.last().observed, Valves::Zero(), nominal_);
      out.cg[i] = t.cg;
      if (out.spread != nullptr) out.spread[i] = t.spread;
      if (out.activity != nullptr) out.activity[i] = t.activity;
    }
    return;
  }
  Valves u;
  for (int k = 0; k < kTanks; ++k) u[k] = actions[i * kTanks + k];
  const StepOutcome& o = e.plant.Step(u);
  const RewardTerms t = ComputeReward(o.observed, u, nominal_);
  WriteState(i, out);
  WriteValves(i, o.valves, out);  // this step's, also when kSameStep starts another episode
  if (out.reward != nullptr) out.reward[i] = t.reward;
  if (out.cg != nullptr) out.cg[i] = t.cg;
  if (out.spread != nullptr) out.spread[i] = t.spread;
  if (out.activity != nullptr) out.activity[i] = t.activity;
  if (out.terminated != nullptr) out.terminated[i] = o.terminal;
  if (out.truncated != nullptr) out.truncated[i] = o.truncated && !o.terminal;
  if (!(o.terminal || o.truncated)) return;
  if (options_.autoreset == Autoreset::kNextStep) {
    e.needs_reset = true;
    return;
  }
  if (out.final_obs != nullptr && out.obs != nullptr)
    std::copy(out.obs + i * kTanks, out.obs + (i + 1) * kTanks, out.final_obs + i * kTanks);
  if (out.final_mask != nullptr) out.final_mask[i] = true;
  StartEpisode(i);
  WriteState(i, out);  // the new episode's observation (age and step: the new episode's)
}

Autoreset ParseAutoreset(const std::string& name) {
  if (name == "next_step") return Autoreset::kNextStep;
  if (name == "same_step") return Autoreset::kSameStep;
  throw std::invalid_argument("autoreset must be 'next_step' or 'same_step', got '" + name + "'");
}

StepMethod ParseStepMethod(const std::string& name) {
  if (name == "closed_form") return StepMethod::kClosedForm;
  if (name == "cvode") return StepMethod::kCvode;
  throw std::invalid_argument("method must be 'closed_form' or 'cvode', got '" + name + "'");
}

}  // namespace ftc
