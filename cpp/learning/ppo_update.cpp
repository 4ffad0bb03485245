// PPO's gradient steps and the actor's forward pass (see ppo_update.h).
//
// The formulae are numpy_ppo_update's (python/ftc/learning/ppo_numpy.py), step
// for step; float32 rounding differs (Eigen's sums, its tanh), which
// tests/python/test_native_ppo.py bounds against the NumPy update.
#include "learning/ppo_update.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>
#include <utility>

namespace ftc::learn {

void ActorCriticShape::Check() const {
  if (trunk.size() < 2 || policy.size() < 2 || value.size() < 2)
    throw std::invalid_argument("actor-critic: the trunk and both heads need a layer each");
  if (policy.front() != trunk.back() || value.front() != trunk.back())
    throw std::invalid_argument("actor-critic: both heads must take the trunk's output width " +
                                std::to_string(trunk.back()));
  for (const auto* widths : {&trunk, &policy, &value})
    for (const int w : *widths)
      if (w <= 0) throw std::invalid_argument("actor-critic: layer widths must be positive");
}

std::size_t ActorCriticShape::Size() const {
  return TanhChain::Size(trunk) + TanhChain::Size(policy) + TanhChain::Size(value);
}

namespace {

float LogSigmoid(float l) { return -Softplus(-l); }

}  // namespace

PpoEpochResult PpoEpoch(float* params, float* adam_m, float* adam_v, std::int64_t* adam_t,
                        const ActorCriticShape& shape, const float* obs, const float* actions,
                        const float* old_logprobs, const float* advantages,
                        const float* returns, int rows, const std::int64_t* order, int n,
                        const PpoOptions& options) {
  shape.Check();
  if (options.minibatch <= 0) throw std::invalid_argument("PpoEpoch: minibatch must be positive");
  for (int i = 0; i < n; ++i)
    if (order[i] < 0 || order[i] >= rows)
      throw std::invalid_argument("PpoEpoch: row index " + std::to_string(order[i]) +
                                  " out of range for " + std::to_string(rows) + " rows");
  const auto size = static_cast<Eigen::Index>(shape.Size());
  const std::size_t trunk_size = TanhChain::Size(shape.trunk);
  const std::size_t policy_size = TanhChain::Size(shape.policy);
  // Own aligned copies (see Distill: Eigen's vectorised sums depend on alignment).
  Eigen::ArrayXf p = Eigen::Map<const Eigen::ArrayXf>(params, size);
  Eigen::ArrayXf m = Eigen::Map<const Eigen::ArrayXf>(adam_m, size);
  Eigen::ArrayXf v = Eigen::Map<const Eigen::ArrayXf>(adam_v, size);
  Eigen::ArrayXf g = Eigen::ArrayXf::Zero(size);
  TanhChain trunk(shape.trunk, true, p.data(), g.data());
  TanhChain policy(shape.policy, false, p.data() + trunk_size, g.data() + trunk_size);
  TanhChain value(shape.value, false, p.data() + trunk_size + policy_size,
                  g.data() + trunk_size + policy_size);

  const int in = shape.trunk.front(), out = shape.policy.back(), vout = shape.value.back();
  const auto clip_lo = static_cast<float>(1.0 - options.clip_coef);
  const auto clip_hi = static_cast<float>(1.0 + options.clip_coef);
  PpoEpochResult result;
  MatrixRM xb, d_logits, d_value, d_trunk, d_trunk_value;
  std::vector<float> ratio, log_ratio, adv;
  for (int start = 0; start < n; start += options.minibatch) {
    const int k = std::min(options.minibatch, n - start);
    const std::int64_t* idx = order + start;
    xb.resize(k, in);
    for (int r = 0; r < k; ++r)
      for (int c = 0; c < in; ++c) xb(r, c) = 2.0f * obs[idx[r] * in + c] - 1.0f;
    const MatrixRM& h = trunk.Forward(xb);
    const MatrixRM& logits = policy.Forward(h);
    const MatrixRM& values = value.Forward(h);

    ratio.resize(k);
    log_ratio.resize(k);
    adv.resize(k);
    double kl = 0, clipped_count = 0, adv_mean = 0;
    for (int r = 0; r < k; ++r) {
      float logprob = 0;
      BernoulliLogProb(&logits(r, 0), actions + idx[r] * out, 1, out, &logprob);
      log_ratio[r] = logprob - old_logprobs[idx[r]];
      ratio[r] = std::exp(log_ratio[r]);
      kl += (ratio[r] - 1.0) - log_ratio[r];
      clipped_count += std::abs(ratio[r] - 1.0f) > options.clip_coef ? 1 : 0;
      adv[r] = advantages[idx[r]];
      adv_mean += adv[r];
    }
    result.approx_kl.push_back(kl / k);
    result.clipfrac.push_back(clipped_count / k);
    if (options.norm_adv && k > 1) {  // mean and sample standard deviation (ddof 1)
      adv_mean /= k;
      double ss = 0;
      for (const float a : adv) ss += (a - adv_mean) * (a - adv_mean);
      const double scale = 1.0 / (std::sqrt(ss / (k - 1)) + 1e-8);
      for (float& a : adv) a = static_cast<float>((a - adv_mean) * scale);
    }

    // the loss and its gradients with respect to the logits and the value
    d_logits.resize(k, out);
    d_value = MatrixRM::Zero(k, vout);
    double pg = 0, vl = 0;
    const auto inv_k = 1.0f / static_cast<float>(k);
    const auto ent = static_cast<float>(options.ent_coef) * inv_k;
    for (int r = 0; r < k; ++r) {
      const float unclipped = -adv[r] * ratio[r];
      const float clipped = -adv[r] * std::clamp(ratio[r], clip_lo, clip_hi);
      pg += std::max(unclipped, clipped);
      // through the ratio wherever the unclipped term is the max (where the
      // two are equal the clip is inactive: the same slope)
      const float d_logprob = (unclipped >= clipped ? unclipped : 0.0f) * inv_k;
      for (int c = 0; c < out; ++c) {
        const float l = logits(r, c), s = Sigmoid(l);
        d_logits(r, c) = d_logprob * (actions[idx[r] * out + c] - s) + ent * s * (1.0f - s) * l;
      }
      const float err = values(r, 0) - returns[idx[r]];
      vl += static_cast<double>(err) * err;
      d_value(r, 0) = static_cast<float>(options.vf_coef) * err * inv_k;
    }
    result.policy_loss = pg / k;
    result.value_loss = 0.5 * vl / k;

    policy.Backward(d_logits, &d_trunk);
    value.Backward(d_value, &d_trunk_value);
    d_trunk += d_trunk_value;
    trunk.Backward(d_trunk, nullptr);
    ClipNorm(g, options.max_grad_norm);
    AdamStep(p, g, m, v, ++*adam_t, options.lr, options.beta1, options.beta2, options.eps);
  }
  Eigen::Map<Eigen::ArrayXf>(params, size) = p;
  Eigen::Map<Eigen::ArrayXf>(adam_m, size) = m;
  Eigen::Map<Eigen::ArrayXf>(adam_v, size) = v;
  return result;
}

Actor::Actor(ActorCriticShape shape, std::vector<const float*> layers)
    : shape_(std::move(shape)), layers_(std::move(layers)) {
  shape_.Check();
  const std::size_t expected =
      2 * (shape_.trunk.size() + shape_.policy.size() + shape_.value.size() - 3);
  if (layers_.size() != expected)
    throw std::invalid_argument("Actor: expected " + std::to_string(expected) +
                                " weight and bias arrays, got " + std::to_string(layers_.size()));
}

const MatrixRM& Actor::Chain(const MatrixRM& x, const std::vector<int>& widths, int first,
                             bool tanh_last, MatrixRM* a, MatrixRM* b) {
  const MatrixRM* in = &x;
  const int n = static_cast<int>(widths.size()) - 1;
  for (int l = 0; l < n; ++l) {
    MatrixRM* z = (l % 2 == 0) ? a : b;
    const ColMap w(layers_[2 * (first + l)], widths[l], widths[l + 1]);
    const Eigen::Map<const Eigen::RowVectorXf> bias(layers_[2 * (first + l) + 1], widths[l + 1]);
    z->noalias() = *in * w;
    z->rowwise() += bias;
    if (l < n - 1 || tanh_last) *z = z->array().tanh().matrix();
    in = z;
  }
  return *in;
}

void Actor::Forward(const float* obs, int rows, float* logits, float* probs, float* values) {
  const int in = shape_.trunk.front(), out = shape_.policy.back();
  const int trunk_layers = static_cast<int>(shape_.trunk.size()) - 1;
  const int policy_layers = static_cast<int>(shape_.policy.size()) - 1;
  x_ = (2.0f * Eigen::Map<const MatrixRM>(obs, rows, in).array() - 1.0f).matrix();
  h_ = Chain(x_, shape_.trunk, 0, true, &t1_, &t2_);
  const MatrixRM& l = Chain(h_, shape_.policy, trunk_layers, false, &t1_, &t2_);
  for (int r = 0; r < rows; ++r)
    for (int c = 0; c < out; ++c) {
      logits[r * out + c] = l(r, c);
      probs[r * out + c] = Sigmoid(l(r, c));
    }
  const MatrixRM& v = Chain(h_, shape_.value, trunk_layers + policy_layers, false, &t1_, &t2_);
  for (int r = 0; r < rows; ++r) values[r] = v(r, 0);
}

void BernoulliLogProb(const float* logits, const float* actions, int rows, int cols,
                      float* log_prob) {
  for (int r = 0; r < rows; ++r) {
    float sum = 0;
    for (int c = 0; c < cols; ++c) {
      const float a = actions[r * cols + c], l = logits[r * cols + c];
      sum += a * LogSigmoid(l) + (1.0f - a) * LogSigmoid(-l);
    }
    log_prob[r] = sum;
  }
}

}  // namespace ftc::learn
