// Dense tanh layers, their backward pass and the behaviour-cloning fit (see tanh_mlp.h).
//
// The formulae are those of python/ftc/learning/ppo_numpy.py (numpy_distill),
// step for step: the same minibatches, loss, clip and Adam. What differs is
// float32 rounding: Eigen sums the products of a matrix product in another
// order than OpenBLAS, and its tanh is another approximation of the same
// function (tests/python/test_native_distill.py bounds the difference).
#include "learning/tanh_mlp.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>
#include <utility>

namespace ftc::learn {

TanhChain::TanhChain(std::vector<int> widths, bool tanh_last, float* params, float* grads)
    : widths_(std::move(widths)), tanh_last_(tanh_last), params_(params), grads_(grads) {
  if (widths_.size() < 2) throw std::invalid_argument("TanhChain: need at least one layer");
  for (const int w : widths_)
    if (w <= 0) throw std::invalid_argument("TanhChain: layer widths must be positive");
  std::size_t offset = 0;
  for (int l = 0; l < layers(); ++l) {
    offsets_.push_back(offset);
    offset += static_cast<std::size_t>(widths_[l] + 1) * static_cast<std::size_t>(widths_[l + 1]);
  }
  acts_.resize(widths_.size());
}

std::size_t TanhChain::Size(const std::vector<int>& widths) {
  std::size_t size = 0;
  for (std::size_t l = 0; l + 1 < widths.size(); ++l)
    size += static_cast<std::size_t>(widths[l] + 1) * static_cast<std::size_t>(widths[l + 1]);
  return size;
}

Eigen::Map<MatrixRM> TanhChain::W(float* base, int layer) const {
  return Eigen::Map<MatrixRM>(base + offsets_[layer], widths_[layer], widths_[layer + 1]);
}

Eigen::Map<Eigen::RowVectorXf> TanhChain::B(float* base, int layer) const {
  const std::size_t at = offsets_[layer] + static_cast<std::size_t>(widths_[layer]) *
                                               static_cast<std::size_t>(widths_[layer + 1]);
  return Eigen::Map<Eigen::RowVectorXf>(base + at, widths_[layer + 1]);
}

const MatrixRM& TanhChain::Forward(const MatrixRM& x) {
  if (x.cols() != widths_.front())
    throw std::invalid_argument("TanhChain::Forward: input has " + std::to_string(x.cols()) +
                                " columns, the first layer takes " +
                                std::to_string(widths_.front()));
  acts_[0] = x;
  for (int l = 0; l < layers(); ++l) {
    MatrixRM& z = acts_[l + 1];
    z.noalias() = acts_[l] * W(params_, l);
    z.rowwise() += B(params_, l);
    if (l < layers() - 1 || tanh_last_) z = z.array().tanh().matrix();
  }
  return acts_.back();
}

void TanhChain::Backward(const MatrixRM& d_output, MatrixRM* d_input) {
  delta_ = d_output;
  for (int l = layers() - 1; l >= 0; --l) {
    if (l < layers() - 1 || tanh_last_)  // tanh' = 1 - tanh^2, at the layer's output
      delta_.array() *= 1.0f - acts_[l + 1].array().square();
    W(grads_, l).noalias() = acts_[l].transpose() * delta_;
    B(grads_, l) = delta_.colwise().sum();
    if (l > 0 || d_input != nullptr) {
      MatrixRM next = delta_ * W(params_, l).transpose();
      delta_.swap(next);
    }
  }
  if (d_input != nullptr) d_input->swap(delta_);
}

void AdamStep(Eigen::ArrayXf& p, const Eigen::ArrayXf& g, Eigen::ArrayXf& m, Eigen::ArrayXf& v,
              std::int64_t t, double lr, double beta1, double beta2, double eps) {
  const auto step = static_cast<double>(t);
  const auto step_size = static_cast<float>(lr / (1.0 - std::pow(beta1, step)));
  const auto root_correction = static_cast<float>(std::sqrt(1.0 - std::pow(beta2, step)));
  m = static_cast<float>(beta1) * m + static_cast<float>(1.0 - beta1) * g;
  v = static_cast<float>(beta2) * v + static_cast<float>(1.0 - beta2) * g.square();
  p -= step_size * (m / (v.sqrt() / root_correction + static_cast<float>(eps)));
}

void ClipNorm(Eigen::ArrayXf& g, double max_norm) {
  const double norm = std::sqrt(static_cast<double>(g.matrix().squaredNorm()));
  const double clip = max_norm / (norm + 1e-6);
  if (clip < 1.0) g *= static_cast<float>(clip);
}

DistillResult Distill(float* params, const std::vector<int>& trunk, const std::vector<int>& head,
                      const float* x, const float* y, const float* w, int n,
                      const std::int64_t* orders, int epochs, const DistillOptions& options) {
  if (trunk.size() < 2 || head.size() < 2 || trunk.back() != head.front())
    throw std::invalid_argument("Distill: the head must take the trunk's output width");
  if (n <= 0) throw std::invalid_argument("Distill: no rows to fit");
  if (options.minibatch <= 0) throw std::invalid_argument("Distill: minibatch must be positive");
  for (long i = 0; i < static_cast<long>(n) * epochs; ++i)
    if (orders[i] < 0 || orders[i] >= n)
      throw std::invalid_argument("Distill: row index " + std::to_string(orders[i]) +
                                  " out of range for " + std::to_string(n) + " rows");
  const int in = trunk.front(), out = head.back();
  const std::size_t trunk_size = TanhChain::Size(trunk);
  const std::size_t size = trunk_size + TanhChain::Size(head);
  Eigen::ArrayXf grads = Eigen::ArrayXf::Zero(static_cast<Eigen::Index>(size));
  Eigen::ArrayXf m = grads, v = grads;
  // The fit works on its own copy of the weights: Eigen's vectorised loops
  // split their work by the data's alignment, and the caller's array (NumPy's)
  // is aligned differently from one allocation to the next, which changed the
  // last bits of the sums from run to run. Its own buffer is always aligned.
  Eigen::ArrayXf p = Eigen::Map<const Eigen::ArrayXf>(params, static_cast<Eigen::Index>(size));
  TanhChain body(trunk, true, p.data(), grads.data());
  TanhChain policy(head, false, p.data() + trunk_size, grads.data() + trunk_size);

  DistillResult result;
  MatrixRM xb, yb, d_logits, d_trunk;
  Eigen::VectorXf wb;
  const int batches = (n + options.minibatch - 1) / options.minibatch;
  while (result.epochs < epochs) {
    const std::int64_t* order = orders + static_cast<long>(result.epochs) * n;
    double total = 0;
    for (int start = 0; start < n; start += options.minibatch) {
      const int rows = std::min(options.minibatch, n - start);
      xb.resize(rows, in);
      yb.resize(rows, out);
      wb.resize(rows);
      for (int r = 0; r < rows; ++r) {
        const std::int64_t i = order[start + r];
        for (int c = 0; c < in; ++c) xb(r, c) = 2.0f * x[i * in + c] - 1.0f;
        for (int c = 0; c < out; ++c) yb(r, c) = y[i * out + c];
        wb[r] = w != nullptr ? w[i] : 1.0f;
      }
      const MatrixRM& logits = policy.Forward(body.Forward(xb));
      // BCE with logits per entry: softplus(l) - y l, slope sigmoid(l) - y; the
      // loss is the (weighted) mean over rows of the mean over valves
      const float norm_w = w != nullptr ? wb.sum() * static_cast<float>(out)
                                        : static_cast<float>(rows) * static_cast<float>(out);
      d_logits.resize(rows, out);
      double loss = 0;
      for (int r = 0; r < rows; ++r) {
        const float scale = wb[r] / norm_w;
        for (int c = 0; c < out; ++c) {
          const float l = logits(r, c), t = yb(r, c);
          loss += static_cast<double>(scale) * (Softplus(l) - t * l);
          d_logits(r, c) = scale * (Sigmoid(l) - t);
        }
      }
      total += loss;
      result.last_loss = loss;
      policy.Backward(d_logits, &d_trunk);
      body.Backward(d_trunk, nullptr);

      // the global norm clip, then Adam, on whole vectors
      ClipNorm(grads, options.max_grad_norm);
      ++result.steps;
      AdamStep(p, grads, m, v, result.steps, options.lr, 0.9, 0.999, options.adam_eps);
    }
    ++result.epochs;
    if (total / batches < options.stop_loss) break;
  }
  Eigen::Map<Eigen::ArrayXf>(params, static_cast<Eigen::Index>(size)) = p;
  return result;
}

}  // namespace ftc::learn
