// PPO's epoch and the actor's forward pass (cpp/learning/ppo_update.h) on cases
// with known answers: the clip stops the policy at ratio 1 + clip_coef, the
// value head learns constant returns, the actor reads torch's layout and
// agrees with the training layout, and bad indices are refused.
// tests/python/test_native_ppo.py compares the same code with the NumPy update.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdint>
#include <numeric>
#include <random>
#include <stdexcept>
#include <vector>

#include "learn_random.h"
#include "learning/ppo_update.h"

namespace ftc::learn {
namespace {

struct Case {
  ActorCriticShape shape{{2, 8}, {8, 1}, {8, 1}};
  int n = 64;
  std::vector<float> params, m, v, obs, actions, old_logprobs, advantages, returns;
  std::vector<std::int64_t> order;

  Case() {
    params = RandomVector(shape.Size(), 1, 0.5f);
    // the policy head's weights and bias zero: every row starts at p = 0.5
    const std::size_t head = TanhChain::Size(shape.trunk);
    std::fill(params.begin() + static_cast<long>(head),
              params.begin() + static_cast<long>(head + TanhChain::Size(shape.policy)), 0.0f);
    m.assign(params.size(), 0.0f);
    v.assign(params.size(), 0.0f);
    obs = RandomVector(static_cast<std::size_t>(n) * 2, 2, 0.3f);
    actions.assign(n, 1.0f);
    old_logprobs.assign(n, std::log(0.5f));
    advantages.assign(n, 1.0f);
    returns.assign(n, 0.7f);
    order.resize(n);
    std::iota(order.begin(), order.end(), 0);
  }

  PpoEpochResult Epoch(const PpoOptions& options, std::int64_t* t) {
    return PpoEpoch(params.data(), m.data(), v.data(), t, shape, obs.data(), actions.data(),
                    old_logprobs.data(), advantages.data(), returns.data(), n, order.data(), n,
                    options);
  }

  // Open probability and value of every row, through the training layout.
  void Evaluate(std::vector<float>* p, std::vector<float>* value) {
    std::vector<float> grads(params.size());
    TanhChain trunk(shape.trunk, true, params.data(), grads.data());
    const std::size_t ts = TanhChain::Size(shape.trunk), ps = TanhChain::Size(shape.policy);
    TanhChain pi(shape.policy, false, params.data() + ts, grads.data() + ts);
    TanhChain val(shape.value, false, params.data() + ts + ps, grads.data() + ts + ps);
    MatrixRM x(n, 2);
    for (int r = 0; r < n; ++r)
      for (int c = 0; c < 2; ++c) x(r, c) = 2.0f * obs[r * 2 + c] - 1.0f;
    const MatrixRM h = trunk.Forward(x);
    const MatrixRM logits = pi.Forward(h), values = val.Forward(h);
    p->resize(n);
    value->resize(n);
    for (int r = 0; r < n; ++r) {
      (*p)[r] = Sigmoid(logits(r, 0));
      (*value)[r] = values(r, 0);
    }
  }
};

// One state, its action always rewarded, advantages not normalised: the
// surrogate pushes p up until the ratio p / 0.5 passes 1 + clip_coef, where
// its gradient is zero. So p stops at 0.5 (1 + clip_coef) plus what Adam's
// momentum carries on (~10 steps of ~1e-3 in the logit: < 0.01 in p), and
// without the clip it runs on towards 1.
TEST(PpoEpoch, TheClipStopsThePolicyAtOnePlusClipCoef) {
  for (const double clip : {0.2, 0.4, 100.0}) {
    Case c;
    for (int r = 0; r < c.n; ++r) c.obs[r * 2] = 0.3f, c.obs[r * 2 + 1] = 0.6f;
    PpoOptions options;
    options.minibatch = 16;
    options.norm_adv = false;
    options.vf_coef = 0.0;
    options.clip_coef = clip;
    options.lr = 2e-4;
    std::int64_t t = 0;
    PpoEpochResult last;
    for (int epoch = 0; epoch < 300; ++epoch) last = c.Epoch(options, &t);
    EXPECT_EQ(t, 300 * 4);  // one Adam step per minibatch
    ASSERT_EQ(last.clipfrac.size(), 4u);
    std::vector<float> p, value;
    c.Evaluate(&p, &value);
    if (clip < 1) {
      EXPECT_GT(p[0], 0.5 * (1 + clip)) << "clip " << clip;
      EXPECT_LT(p[0], 0.5 * (1 + clip) + 0.01) << "clip " << clip;
      EXPECT_EQ(last.clipfrac.back(), 1.0);  // every row past the clip
      EXPECT_NEAR(last.policy_loss, -(1 + clip), 1e-6);  // where the surrogate is flat
    } else {
      EXPECT_GT(p[0], 0.8);  // 0.84: far past any clip
    }
  }
}

// Advantages zero (no policy gradient), constant returns: the value head
// learns the constant; the loss it reports falls to near zero.
TEST(PpoEpoch, TheValueHeadLearnsConstantReturns) {
  Case c;
  std::fill(c.advantages.begin(), c.advantages.end(), 0.0f);
  PpoOptions options;
  options.minibatch = c.n;  // full batches: no minibatch noise to jitter the fit
  options.lr = 1e-2;
  std::int64_t t = 0;
  const double first = c.Epoch(options, &t).value_loss;
  PpoEpochResult last;
  for (int epoch = 0; epoch < 1000; ++epoch) last = c.Epoch(options, &t);
  std::vector<float> p, value;
  c.Evaluate(&p, &value);
  for (int r = 0; r < c.n; ++r) EXPECT_NEAR(value[r], 0.7f, 0.03f) << "row " << r;
  EXPECT_LT(last.value_loss, 5e-5);  // 0.5 x 0.01^2: the rows within 0.01 r.m.s.
  EXPECT_GT(first, 10 * last.value_loss);
  for (const double kl : last.approx_kl) EXPECT_NEAR(kl, 0.0, 1e-6);  // the policy never moved
}

TEST(PpoEpoch, RefusesRowIndicesOutOfRange) {
  Case c;
  c.order[5] = c.n;
  std::int64_t t = 0;
  EXPECT_THROW(c.Epoch(PpoOptions{}, &t), std::invalid_argument);
  EXPECT_EQ(t, 0);
  c.order[5] = 5;
  c.shape.value = {4, 1};  // does not take the trunk's width
  EXPECT_THROW(c.Epoch(PpoOptions{}, &t), std::invalid_argument);
}

// The actor reads each weight as torch stores it, (out, in) row-major; the
// same network in the training layout (W (in, out)) gives the same outputs.
TEST(Actor, ReadsTorchsLayoutAndAgreesWithTheTrainingLayout) {
  const ActorCriticShape shape{{3, 5, 4}, {4, 3, 2}, {4, 2, 1}};
  const std::vector<float> flat = RandomVector(shape.Size(), 7, 0.6f);
  // torch's copy: per layer the transposed weight, then the bias
  std::vector<std::vector<float>> torch_layers;
  std::size_t at = 0;
  for (const auto* widths : {&shape.trunk, &shape.policy, &shape.value})
    for (std::size_t l = 0; l + 1 < widths->size(); ++l) {
      const int in = (*widths)[l], out = (*widths)[l + 1];
      std::vector<float> w(static_cast<std::size_t>(in * out));
      for (int i = 0; i < in; ++i)
        for (int o = 0; o < out; ++o) w[o * in + i] = flat[at + i * out + o];
      at += static_cast<std::size_t>(in * out);
      torch_layers.push_back(w);
      torch_layers.emplace_back(flat.begin() + static_cast<long>(at),
                                flat.begin() + static_cast<long>(at + out));
      at += static_cast<std::size_t>(out);
    }
  std::vector<const float*> pointers;
  for (const auto& a : torch_layers) pointers.push_back(a.data());
  Actor actor(shape, pointers);
  const int rows = 5;
  const std::vector<float> obs = RandomVector(rows * 3, 8, 0.5f);
  std::vector<float> logits(rows * 2), probs(rows * 2), values(rows), log_prob(rows);
  actor.Forward(obs.data(), rows, logits.data(), probs.data(), values.data());

  std::vector<float> params = flat, grads(flat.size());
  const std::size_t ts = TanhChain::Size(shape.trunk), ps = TanhChain::Size(shape.policy);
  TanhChain trunk(shape.trunk, true, params.data(), grads.data());
  TanhChain pi(shape.policy, false, params.data() + ts, grads.data() + ts);
  TanhChain val(shape.value, false, params.data() + ts + ps, grads.data() + ts + ps);
  MatrixRM x = (2.0f * Eigen::Map<const MatrixRM>(obs.data(), rows, 3).array() - 1.0f).matrix();
  const MatrixRM h = trunk.Forward(x);
  const MatrixRM expect_logits = pi.Forward(h), expect_values = val.Forward(h);
  const std::vector<float> actions{1, 0, 0, 1, 1, 1, 0, 0, 1, 0};
  BernoulliLogProb(logits.data(), actions.data(), rows, 2, log_prob.data());
  for (int r = 0; r < rows; ++r) {
    EXPECT_NEAR(values[r], expect_values(r, 0), 1e-6f);
    double expect_lp = 0;
    for (int k = 0; k < 2; ++k) {
      EXPECT_NEAR(logits[r * 2 + k], expect_logits(r, k), 1e-6f);
      EXPECT_NEAR(probs[r * 2 + k], 1.0 / (1.0 + std::exp(-expect_logits(r, k))), 1e-6);
      const double p = probs[r * 2 + k];
      expect_lp += std::log(actions[r * 2 + k] > 0 ? p : 1.0 - p);
    }
    EXPECT_NEAR(log_prob[r], expect_lp, 1e-5);
  }
  EXPECT_THROW(Actor(shape, std::vector<const float*>(pointers.begin(), pointers.end() - 1)),
               std::invalid_argument);
}

}  // namespace
}  // namespace ftc::learn
