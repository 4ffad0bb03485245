// PPO's gradient steps and the actor's forward pass for acting, in C++: the
// arithmetic of python/ftc/learning/ppo_numpy.py (numpy_ppo_update and
// NumpyActor) on the same flat float32 parameters, so the NumPy engine can hand
// its inner loops to this code (bindings.cpp: ftc._learn).
//
// Why: an offline phase takes 64 Adam steps of 64 rows per update and acts
// once per model step; each is ~40 NumPy calls of a few microseconds on
// arrays of a few hundred floats (docs/benchmarks.md, seventh round).
//
// The actor-critic: a tanh trunk over 2 obs - 1, then a policy head (logits
// of independent Bernoulli valves) and a value head (its first output), each
// tanh between layers and linear at the end.
#pragma once

#include <cstdint>
#include <vector>

#include "learning/tanh_mlp.h"

namespace ftc::learn {

struct ActorCriticShape {
  std::vector<int> trunk;   // input width, then each trunk layer's width
  std::vector<int> policy;  // trunk.back(), then each policy layer's width
  std::vector<int> value;   // trunk.back(), then each value layer's width
  // Throws std::invalid_argument unless the three chain (and the value head
  // ends in at least one output).
  void Check() const;
  std::size_t Size() const;  // floats of all parameters: trunk, policy, value
};

struct PpoOptions {
  int minibatch = 64;
  double clip_coef = 0.2;
  double ent_coef = 0.0;
  double vf_coef = 0.5;
  double max_grad_norm = 0.5;
  bool norm_adv = true;
  double lr = 3e-4;
  double beta1 = 0.9;
  double beta2 = 0.999;
  double eps = 1e-5;
};

struct PpoEpochResult {
  std::vector<double> approx_kl;  // per minibatch: mean of (ratio - 1) - log ratio
  std::vector<double> clipfrac;   // per minibatch: fraction with |ratio - 1| > clip_coef
  double policy_loss = 0;         // the last minibatch's clipped surrogate
  double value_loss = 0;          // the last minibatch's 0.5 mean squared error
};

// One epoch of PPO over the rows in `order` (n indices into the data, taken
// minibatch by minibatch): the clipped surrogate with advantages normalised
// per minibatch (norm_adv, minibatches of 2 or more rows), the entropy bonus,
// the value loss, the global gradient-norm clip and Adam with torch's
// formulae. params, adam_m, adam_v: Size() floats each, updated in place;
// *adam_t: Adam's step count, advanced once per minibatch.
// Data: obs (rows x trunk[0]), actions (rows x policy.back()), old_logprobs,
// advantages and returns (rows), all row-major float32.
// Throws std::invalid_argument on indices out of range.
PpoEpochResult PpoEpoch(float* params, float* adam_m, float* adam_v, std::int64_t* adam_t,
                        const ActorCriticShape& shape, const float* obs, const float* actions,
                        const float* old_logprobs, const float* advantages,
                        const float* returns, int rows, const std::int64_t* order, int n,
                        const PpoOptions& options);

// The actor's forward pass for acting: logits and their sigmoids (rows x
// policy.back()) and values (rows) of obs (rows x trunk[0]), with parameters
// given layer by layer as torch holds them (each weight (out, in) row-major,
// then its bias) so that they are read where torch keeps them, without copies.
class Actor {
 public:
  // layers: pointers to each Linear's weight then bias, trunk then policy then
  // value head, in torch's parameter order. Not owned: they must outlive this.
  Actor(ActorCriticShape shape, std::vector<const float*> layers);

  void Forward(const float* obs, int rows, float* logits, float* probs, float* values);

 private:
  using ColMap = Eigen::Map<const Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic>>;
  // x -> tanh(x W1 + b1) -> ... ending linear unless tanh_last; layers from `first`.
  const MatrixRM& Chain(const MatrixRM& x, const std::vector<int>& widths, int first,
                        bool tanh_last, MatrixRM* a, MatrixRM* b);

  ActorCriticShape shape_;
  std::vector<const float*> layers_;
  MatrixRM x_, h_, t1_, t2_;
};

// Sum over columns of a log Bernoulli(sigmoid(logit)) of each 0/1 action:
// log_prob[r] = sum_c a log sigmoid(l) + (1 - a) log sigmoid(-l).
void BernoulliLogProb(const float* logits, const float* actions, int rows, int cols,
                      float* log_prob);

}  // namespace ftc::learn
