// The plant pool (pool.h): each env is a Plant stepped as one alone would be,
// whatever the thread count; the closed-form step method stays within CVODE's
// tolerances; the worker pool runs every index once and rethrows.
#include <gtest/gtest.h>

#include <algorithm>
#include <atomic>
#include <memory>
#include <random>
#include <stdexcept>
#include <vector>

#include "plant/core/pool.h"
#include "plant/core/reward.h"

namespace ftc {
namespace {

struct Buffers {
  explicit Buffers(int n)
      : obs(6 * n), reward(n), age(n), cg(n), spread(n), activity(n), step(n),
        terminated(new bool[n]()), truncated(new bool[n]()) {}
  PoolOutput Out() {
    PoolOutput o;
    o.obs = obs.data();
    o.reward = reward.data();
    o.terminated = terminated.get();
    o.truncated = truncated.get();
    o.age = age.data();
    o.episode_step = step.data();
    o.cg = cg.data();
    o.spread = spread.data();
    o.activity = activity.data();
    return o;
  }
  std::vector<float> obs;
  std::vector<double> reward, age, cg, spread, activity;
  std::vector<std::int64_t> step;
  std::unique_ptr<bool[]> terminated, truncated;
};

FaultScenario Worn(int k) {
  FaultScenario s;
  s.steps_per_interval = 40;
  s.engine_factor[k % 2] = 5.0 + k;
  s.tank_factor[k % 6] = 8.0 + k;
  return s;
}

TEST(Pool, EachEnvIsAPlantSteppedAloneForAnyThreadCount) {
  // The same Plant code on the same inputs: equal to the last bit (EXPECT_EQ).
  const int n = 40, steps = 100;
  std::vector<FaultScenario> scenarios;
  std::vector<std::uint64_t> seeds;
  for (int k = 0; k < n; ++k) {
    scenarios.push_back(Worn(k));
    seeds.push_back(100 + k);
  }
  std::mt19937_64 rng(4);
  std::vector<std::int8_t> actions(static_cast<std::size_t>(steps) * n * 6);
  for (auto& a : actions) a = static_cast<std::int8_t>(rng() & 1);
  for (const int threads : {1, 3}) {
    PoolOptions options;
    options.method = StepMethod::kCvode;
    options.threads = threads;
    PlantPool pool(scenarios, seeds, options);
    Buffers b(n);
    pool.Reset(b.Out());
    std::vector<Plant> alone;
    for (int k = 0; k < n; ++k) {
      alone.emplace_back(scenarios[k], seeds[k]);
      alone.back().Reset();
    }
    std::vector<bool> ended(n, false);
    for (int t = 0; t < steps; ++t) {
      const std::int8_t* u = actions.data() + static_cast<std::size_t>(t) * n * 6;
      pool.Step(u, b.Out());
      for (int k = 0; k < n; ++k) {
        if (ended[k]) {  // kNextStep: this step was the reset
          alone[k].Reset();
          ended[k] = false;
          EXPECT_EQ(b.reward[k], 0.0);
          continue;
        }
        Valves v;
        for (int i = 0; i < 6; ++i) v[i] = u[k * 6 + i];
        const StepOutcome& o = alone[k].Step(v);
        ASSERT_EQ(b.reward[k], ComputeReward(o.observed, v, PlantParams{}).reward);
        ASSERT_EQ(b.obs[k * 6], static_cast<float>(std::clamp(o.observed[0], 0.0, 1.0)));
        ASSERT_EQ(b.terminated[k], o.terminal);
        ASSERT_EQ(b.age[k], o.age);
        ended[k] = o.terminal || o.truncated;
      }
    }
  }
}

TEST(Pool, ClosedFormPlantStaysWithinCvodeTolerance) {
  // CVODE at rtol 1e-8 is within 2.5e-8 m per step of an exact step (integrator.cpp);
  // the closed form is exact up to rounding. 1e-6 m over an episode of up to 59
  // steps leaves room for that error to add up.
  for (int k = 0; k < 12; ++k) {
    Plant cvode(Worn(k), 0), closed(Worn(k), 0, PlantParams{}, {}, StepMethod::kClosedForm);
    cvode.Reset();
    closed.Reset();
    std::mt19937_64 rng(k);
    for (int t = 0; t < 120; ++t) {
      Valves u;
      for (int i = 0; i < 6; ++i) u[i] = static_cast<int>(rng() & 1);
      const StepOutcome& a = cvode.Step(u);
      const StepOutcome& b = closed.Step(u);
      ASSERT_LT((a.level - b.level).cwiseAbs().maxCoeff(), 1e-6) << "scenario " << k;
      ASSERT_EQ(a.terminal, b.terminal);
    }
  }
}

TEST(Pool, WorkersRunEveryIndexOnceAndRethrow) {
  Workers workers(3);
  std::vector<std::atomic<int>> hits(1000);
  workers.Run(1000, [&](int i) { hits[i]++; });
  for (const auto& h : hits) EXPECT_EQ(h.load(), 1);
  EXPECT_THROW(workers.Run(500, [](int i) {
                 if (i == 321) throw std::runtime_error("env 321");
               }),
               std::runtime_error);
  workers.Run(1000, [&](int i) { hits[i]++; });  // still usable
  for (const auto& h : hits) EXPECT_EQ(h.load(), 2);
}

TEST(Pool, DistributionIsValidatedAndItsDrawsAreChecked) {
  ScenarioDistribution d;
  d.stuck_valve_probability = 0.5;
  d.dead_pump_probability = 0.5;
  for (const FaultScenario& s : DrawScenarios(d, 300, 9)) EXPECT_NO_THROW(d.Check(s));
  d.event_factor = {5.0, 1.0};
  EXPECT_THROW(d.Validate(), std::invalid_argument);
}

}  // namespace
}  // namespace ftc
