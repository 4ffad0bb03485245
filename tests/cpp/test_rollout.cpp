// Batch rollouts (rollout.h): the closed-form idle-conduit step against CVODE,
// batches against the Plant stepped one step at a time (episode resets
// included), and the caches (shared prefixes, closed form) against plain runs.
#include <gtest/gtest.h>

#include <limits>
#include <random>
#include <vector>

#include "plant/core/plant.h"
#include "plant/core/reward.h"
#include "plant/core/rollout.h"

namespace ftc {
namespace {

FaultScenario SingleFault() {
  FaultScenario s;
  s.engine_factor[0] = 20.0;
  return s;
}

Valves FromCode(int code) {
  Valves u;
  for (int i = 0; i < kTanks; ++i) u[i] = (code >> i) & 1;
  return u;
}

// "Action held for `hold` steps, then all closed" for every action.
std::vector<Valves> HoldThenClosed(int hold, int horizon) {
  std::vector<Valves> seq;
  for (int a = 0; a < 64; ++a)
    for (int t = 0; t < horizon; ++t) seq.push_back(t < hold ? FromCode(a) : Valves::Zero());
  return seq;
}

TEST(IdleConduitStep, MatchesCvodeIncludingTanksRunningDry) {
  const PlantParams p = DegradedParams(PlantParams{}, SingleFault(), 9.0);
  StepIntegrator integrator;
  Vec6 x;
  x << 0.5, 0.02, 0.03, 0.7, 0.0, 0.9;  // tanks 2 and 3 run dry within the step
  for (const int code : {0, 1, 2, 4, 8, 16, 32}) {
    const Valves u = FromCode(code);
    const StepResult exact = IdleConduitStep(x, u, p, 1.0);
    const StepResult cvode = integrator.Step(x, u, p, 1.0);
    EXPECT_LT((exact.x - cvode.x).cwiseAbs().maxCoeff(), 1e-8) << "valves " << code;
    EXPECT_LT((exact.supplied - cvode.supplied).cwiseAbs().maxCoeff(), 1e-8);
    EXPECT_LT((exact.deficit - cvode.deficit).cwiseAbs().maxCoeff(), 1e-8);
    EXPECT_EQ(exact.events, 2);
  }
  EXPECT_THROW(IdleConduitStep(x, FromCode(3), p, 1.0), std::invalid_argument);
}

TEST(BatchRollout, EqualsThePlantSteppedOneStepAtATimeAcrossAnEpisodeReset) {
  // Age 5 of the single fault; 70 steps cross the end of the first episode
  // (about 55 steps), so the rollout's reset to full tanks is exercised.
  const FaultScenario s = SingleFault();
  const int horizon = 70;
  std::mt19937_64 rng(3);
  std::vector<Valves> seq;
  const int candidates = 4;
  for (int k = 0; k < candidates; ++k) {
    for (int t = 0; t < horizon; ++t) {
      // hold a random setting for a few steps at a time, closed half of the time
      const int code = (t % 5 == 0 || t == 0) ? static_cast<int>(rng() % 64) : -1;
      seq.push_back(code >= 0 ? (code % 2 ? FromCode(code) : Valves::Zero()) : seq.back());
    }
  }
  BatchRollout rollout;
  const PlantParams p = DegradedParams(PlantParams{}, s, 5.0);
  const RolloutResult r = rollout.Run(Vec6::Ones(), seq, candidates, horizon, {p});
  for (int k = 0; k < candidates; ++k) {
    Plant plant(s, 0);
    plant.SetOperatingSteps(5 * s.steps_per_interval);
    plant.Reset();
    double total = 0;
    int resets = 0;
    for (int t = 0; t < horizon; ++t) {
      const Valves& u = seq[k * horizon + t];
      const StepOutcome& o = plant.Step(u);  // starts a new episode after a terminal one
      ASSERT_DOUBLE_EQ(o.age, 5.0);
      const double rew = ComputeReward(o.level, u, p).reward;
      EXPECT_NEAR(r.rewards[k * horizon + t], rew, 1e-6) << "candidate " << k << " step " << t;
      EXPECT_LT((r.levels[k * horizon + t] - o.level).cwiseAbs().maxCoeff(), 1e-6);
      EXPECT_EQ(r.terminal[k * horizon + t] != 0, o.terminal);
      resets += o.terminal ? 1 : 0;
      total += rew;
    }
    EXPECT_EQ(resets, 1);
    EXPECT_NEAR(r.total[k], total, 1e-5);
  }
}

TEST(BatchRollout, CachesDoNotChangeTheResult) {
  const PlantParams p = DegradedParams(PlantParams{}, SingleFault(), 9.0);
  Vec6 x0;
  x0 << 0.2, 0.3, 0.25, 0.6, 0.7, 0.65;
  std::vector<Valves> seq = HoldThenClosed(3, 10);
  // candidates with a shared prefix (two settings, then varied)
  for (int a = 0; a < 8; ++a)
    for (int t = 0; t < 10; ++t) seq.push_back(t < 2 ? FromCode(45) : FromCode(a * 7 % 64));
  const int k = static_cast<int>(seq.size()) / 10;
  BatchRollout fast;
  RolloutOptions plain_options;
  plain_options.exact_idle_conduit = false;
  plain_options.share_prefixes = false;
  BatchRollout plain({}, plain_options);
  const RolloutResult a = fast.Run(x0, seq, k, 10, {p});
  const RolloutResult b = plain.Run(x0, seq, k, 10, {p});
  EXPECT_GT(a.shared_steps, 8 * 2 - 2);
  EXPECT_GT(a.exact_steps, 64 * 7);
  EXPECT_EQ(b.shared_steps, 0);
  EXPECT_EQ(b.exact_steps, 0);
  for (int c = 0; c < k; ++c) EXPECT_NEAR(a.total[c], b.total[c], 1e-6) << "candidate " << c;
}

TEST(BatchRollout, PerStepParamsApplyToTheirStep) {
  // Demand doubled from step 2 on shortens the episode: the per-step list is used.
  const PlantParams p = PlantParams{};
  PlantParams hungry = p;
  hungry.demand *= 2.0;
  const std::vector<Valves> seq(3, Valves::Zero());
  BatchRollout rollout;
  const RolloutResult r = rollout.Run(Vec6::Ones(), seq, 1, 3, {p, hungry, hungry});
  EXPECT_NEAR(r.levels[0].sum(), 6.0 - 0.1, 1e-9);
  EXPECT_NEAR(r.levels[2].sum(), 6.0 - 0.1 - 2 * 0.2, 1e-9);
  EXPECT_THROW(rollout.Run(Vec6::Ones(), seq, 1, 3, {p, p}), std::invalid_argument);
}

TEST(BatchRollout, StepEachEqualsOneStepRunsAndMarksRefusedRows) {
  // Rows of a trajectory (each continuing the last, so CVODE continues warm) and
  // unrelated rows; every row bit-identical to a one-step Run on a fresh
  // object fed the same rows in the same order. A NaN level makes CVODE's
  // right-hand side fail: that row is NaN and counted, the next goes on.
  const PlantParams p = DegradedParams(PlantParams{}, SingleFault(), 3.0);
  std::mt19937_64 rng(5);
  std::vector<Vec6> x;
  std::vector<Valves> u;
  Vec6 level = Vec6::Constant(0.9);
  BatchRollout stepper;
  for (int t = 0; t < 40; ++t) {
    const Valves v = FromCode(t < 20 ? 0b000110 : static_cast<int>(rng() % 64));
    x.push_back(t % 3 == 2 ? Vec6::Constant(0.5) : level);
    u.push_back(v);
    level = stepper.Run(x.back(), {v}, 1, 1, {p}).levels[0];
  }
  x.push_back(Vec6::Constant(std::numeric_limits<double>::quiet_NaN()));
  u.push_back(FromCode(0b000011));
  x.push_back(Vec6::Constant(0.5));
  u.push_back(FromCode(0b000011));
  BatchRollout reference, batch;
  long refused = 0;
  const std::vector<Vec6> got = batch.StepEach(x, u, p, 1.0, &refused);
  ASSERT_EQ(got.size(), x.size());
  for (std::size_t n = 0; n + 2 < x.size(); ++n) {
    const Vec6 want = reference.Run(x[n], {u[n]}, 1, 1, {p}).levels[0];
    EXPECT_TRUE((got[n].array() == want.array()).all()) << "row " << n;
  }
  EXPECT_TRUE(got[x.size() - 2].array().isNaN().all());
  EXPECT_TRUE(got.back().allFinite());
  EXPECT_EQ(refused, 1);
  EXPECT_THROW(batch.StepEach(x, {u[0]}, p), std::invalid_argument);
}

}  // namespace
}  // namespace ftc
