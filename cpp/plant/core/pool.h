// A batch of plants stepped by one call: N Plants (plant.h), each with its own
// scenario and seed, advanced in parallel by a pool of std::threads, results
// written into caller-owned arrays (the Python binding hands NumPy's buffers
// over as they are). EnvPool's shape, without its asynchronous half: one
// synchronous step of the whole batch per call.
//
// Each env is exactly a Plant driven as FuelTransferEnv drives one: step,
// and after a terminal or truncated step a new episode at the plant's age
// (Plant::Reset), so an env ages over intervals as the single env does. The
// reward is ComputeReward (reward.cpp) of the published levels after the step
// and the commanded valves, as FuelTransferEnv computes it; the observation
// the published levels clipped to [0, 1] as float32.
#pragma once

#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <exception>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "plant/core/plant.h"
#include "plant/core/scenario_distribution.h"

namespace ftc {

// What happens to an env after a step that ends its episode (Gymnasium 1.x's
// AutoresetMode). kNextStep: the next Step resets it instead of stepping
// (reward 0, not done, its action ignored). kSameStep: it is reset within the
// same Step; the observation written is the new episode's, the last one goes to
// final_obs (final_mask set).
enum class Autoreset { kNextStep, kSameStep };

struct PoolOptions {
  StepMethod method = StepMethod::kClosedForm;
  int threads = 0;  // 0: std::thread::hardware_concurrency(); 1: the caller's thread only
  Autoreset autoreset = Autoreset::kNextStep;
  // > 0: an env whose plant has run this many intervals is renewed when its
  // next episode starts: a fresh plant (age 0), seeded MixSeed(seed, life),
  // with a scenario drawn anew from the distribution if there is one (else the
  // same scenario). 0: plants age forever, as a single env does.
  int life_intervals = 0;
};

// Caller-owned outputs, N rows each (N x 6 for obs and final_obs). A null
// pointer is not written.
struct PoolOutput {
  float* obs = nullptr;
  double* reward = nullptr;
  bool* terminated = nullptr;
  bool* truncated = nullptr;
  double* age = nullptr;                // age in force during the step, intervals
  std::int64_t* episode_step = nullptr; // steps taken in the current episode
  double* cg = nullptr;                 // reward terms (reward.h)
  double* spread = nullptr;
  double* activity = nullptr;
  float* final_obs = nullptr;           // kSameStep: the observation that ended an episode
  bool* final_mask = nullptr;           // kSameStep: whether final_obs[i] was written
  std::int8_t* valves = nullptr;        // (N, 6) valves applied during the step just taken
                                        // (stuck ones as they stayed; 0 after a reset)
};

// A fixed set of worker threads running one index loop at a time; the caller
// works too. Indices are handed out in chunks from an atomic counter, so a slow
// env (CVODE after a pinned tank) does not hold a whole static share.
class Workers final {
 public:
  explicit Workers(int threads);
  ~Workers();
  Workers(const Workers&) = delete;
  Workers& operator=(const Workers&) = delete;

  // task(i) for every i in [0, n); returns when all are done. The first
  // exception a task throws is rethrown here (after every index has run).
  void Run(int n, const std::function<void(int)>& task);
  int threads() const { return static_cast<int>(threads_.size()) + 1; }

 private:
  void Loop();
  void Drain();

  std::vector<std::thread> threads_;
  std::mutex mutex_;
  std::condition_variable wake_, done_;
  const std::function<void(int)>* task_ = nullptr;
  int n_ = 0;
  std::atomic<int> next_{0};
  int busy_ = 0;
  std::uint64_t generation_ = 0;
  bool stop_ = false;
  std::exception_ptr error_;
};

class PlantPool final {
 public:
  // One env per scenario, seeded seeds[i] (as many as scenarios). With a
  // distribution, renewed plants (PoolOptions::life_intervals) draw from it.
  // Throws std::invalid_argument on mismatched sizes, no env, or bad options.
  PlantPool(const std::vector<FaultScenario>& scenarios, const std::vector<std::uint64_t>& seeds,
            const PoolOptions& options, const ScenarioDistribution* distribution = nullptr);
  PlantPool(const PlantPool&) = delete;
  PlantPool& operator=(const PlantPool&) = delete;

  int size() const { return static_cast<int>(envs_.size()); }
  int threads() const { return workers_.threads(); }
  const PoolOptions& options() const { return options_; }
  const Plant& plant(int i) const { return envs_.at(static_cast<std::size_t>(i)).plant; }

  // Fresh plants (age 0) with these seeds and scenarios (sizes as constructed).
  void Reseed(const std::vector<FaultScenario>& scenarios, const std::vector<std::uint64_t>& seeds);
  // A new episode in every env at its age (renewing those past their life);
  // writes obs, age and episode_step, zero reward, not done.
  void Reset(const PoolOutput& out);
  // One control step of every env; actions: N x 6 valves, each 0 or 1 (the
  // caller checks). See Autoreset for envs whose episode ended.
  void Step(const std::int8_t* actions, const PoolOutput& out);

 private:
  struct Env {
    Plant plant;
    std::uint64_t seed = 0;
    std::int64_t life = 0;
    bool needs_reset = false;
  };
  void StartEpisode(int i);
  void WriteState(int i, const PoolOutput& out) const;
  static void WriteValves(int i, const Valves& applied, const PoolOutput& out);
  void StepOne(int i, const std::int8_t* actions, const PoolOutput& out);

  static constexpr int kValveMasks = 1 << kTanks;

  PoolOptions options_;
  std::unique_ptr<ScenarioDistribution> distribution_;
  PlantParams nominal_;
  std::vector<Env> envs_;
  std::vector<std::uint8_t> masks_;  // Step's scratch: each env's valves as 6 bits
  std::vector<int> order_;           // and the envs sorted by them
  Workers workers_;
};

Autoreset ParseAutoreset(const std::string& name);
StepMethod ParseStepMethod(const std::string& name);

}  // namespace ftc
