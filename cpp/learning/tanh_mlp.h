// The policy network's arithmetic for behaviour cloning, in C++: a chain of
// dense layers with tanh, its backward pass, the global gradient-norm clip and
// Adam, over flat float32 parameter vectors laid out as the NumPy engine's
// (python/ftc/learning/ppo_numpy.py: each layer's W as (in, out) row-major,
// then its b). No Python here; bindings.cpp exposes it as ftc._learn.
//
// Why: a distillation step on 128 rows of the 6-64-64 trunk and 64-16-16-6
// head is ~30 NumPy calls of a few microseconds each; the arithmetic itself
// is a few tens of microseconds. See docs/benchmarks.md (sixth round).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include <Eigen/Core>

namespace ftc::learn {

using MatrixRM = Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;

// log(1 + e^l), without overflow.
inline float Softplus(float l) { return std::max(l, 0.0f) + std::log1p(std::exp(-std::abs(l))); }

inline float Sigmoid(float l) {
  if (l >= 0) return 1.0f / (1.0f + std::exp(-l));
  const float e = std::exp(l);
  return e / (1.0f + e);
}

// Adam's update of p from the gradient g with moments m, v at step t (1 for
// the first), torch's formulae; whole vectors.
void AdamStep(Eigen::ArrayXf& p, const Eigen::ArrayXf& g, Eigen::ArrayXf& m, Eigen::ArrayXf& v,
              std::int64_t t, double lr, double beta1, double beta2, double eps);

// Scales g so that its L2 norm is at most max_norm (torch's clip_grad_norm_:
// the factor max_norm / (norm + 1e-6), applied only when below 1).
void ClipNorm(Eigen::ArrayXf& g, double max_norm);

// Dense layers x -> tanh(x W1 + b1) -> ... -> x Wn + bn (tanh after the last
// too if tanh_last), on parameters and gradients held elsewhere (views).
class TanhChain {
 public:
  // widths: input width, then each layer's output width (>= 2 entries).
  // params/grads: at least Size(widths) floats each; not owned.
  TanhChain(std::vector<int> widths, bool tanh_last, float* params, float* grads);

  // Number of floats the layers of `widths` take (weights and biases).
  static std::size_t Size(const std::vector<int>& widths);

  // Output (B, last width) for input (B, first width); keeps the activations.
  const MatrixRM& Forward(const MatrixRM& x);

  // Writes the gradients of the loss into grads, given its gradient with
  // respect to the last Forward's output; the gradient with respect to the
  // input into *d_input unless it is null.
  void Backward(const MatrixRM& d_output, MatrixRM* d_input);

  int layers() const { return static_cast<int>(widths_.size()) - 1; }

 private:
  Eigen::Map<MatrixRM> W(float* base, int layer) const;
  Eigen::Map<Eigen::RowVectorXf> B(float* base, int layer) const;

  std::vector<int> widths_;
  std::vector<std::size_t> offsets_;  // start of each layer's W; its b follows W
  bool tanh_last_;
  float* params_;
  float* grads_;
  std::vector<MatrixRM> acts_;  // input, then each layer's output
  MatrixRM delta_;
};

struct DistillOptions {
  int minibatch = 128;
  double lr = 1e-3;
  double max_grad_norm = 0.5;
  double stop_loss = 0.0;  // stop after an epoch whose mean minibatch loss is below it
  double adam_eps = 1e-5;
};

struct DistillResult {
  double last_loss = 0;  // the last minibatch's loss
  int epochs = 0;        // epochs run
  long steps = 0;        // Adam steps taken
};

// Behaviour cloning of 0/1 valve labels into a policy's logits: binary
// cross-entropy of head(trunk(2 x - 1)) against y, averaged over the valves and
// over a minibatch's rows (weighted by w when given), the global norm clip over
// all the parameters, and a fresh Adam (torch's formulae, betas 0.9 / 0.999).
//   params: trunk then head parameters (TanhChain layout), updated in place;
//   x, y: n x in and n x out row-major; w: n weights or null;
//   orders: epochs x n row indices, one permutation per epoch.
// Throws std::invalid_argument on inconsistent sizes or indices out of range.
DistillResult Distill(float* params, const std::vector<int>& trunk, const std::vector<int>& head,
                      const float* x, const float* y, const float* w, int n,
                      const std::int64_t* orders, int epochs, const DistillOptions& options);

}  // namespace ftc::learn
