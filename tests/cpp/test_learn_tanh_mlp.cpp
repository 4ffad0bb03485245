// The learning kernels (cpp/learning/tanh_mlp.h): the backward pass against
// finite differences, behaviour cloning on a case with a known answer, row
// weights against repeated rows, and the errors.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <numeric>
#include <random>
#include <stdexcept>
#include <vector>

#include "learn_random.h"
#include "learning/tanh_mlp.h"

namespace ftc::learn {
namespace {

// Loss c . f(x) summed over rows: its gradient with respect to the output is c.
double Loss(TanhChain& chain, const MatrixRM& x, const MatrixRM& c) {
  return static_cast<double>(chain.Forward(x).cwiseProduct(c).sum());
}

TEST(TanhChain, BackwardEqualsFiniteDifferences) {
  const std::vector<int> widths{3, 5, 4, 2};
  for (const bool tanh_last : {false, true}) {
    std::vector<float> params = RandomVector(TanhChain::Size(widths), 1, 0.7f);
    std::vector<float> grads(params.size(), 0.0f);
    TanhChain chain(widths, tanh_last, params.data(), grads.data());
    const std::vector<float> xs = RandomVector(4 * 3, 2, 1.0f);
    const std::vector<float> cs = RandomVector(4 * 2, 3, 1.0f);
    const MatrixRM x = Eigen::Map<const MatrixRM>(xs.data(), 4, 3);
    const MatrixRM c = Eigen::Map<const MatrixRM>(cs.data(), 4, 2);
    chain.Forward(x);
    MatrixRM d_input;
    chain.Backward(c, &d_input);
    // Central differences in float32 with h = 1e-2: truncation error ~h^2 times
    // the third derivative (< 1e-3 here), rounding ~1e-7 / h = 1e-5; 2e-3 holds both.
    const float h = 1e-2f;
    for (std::size_t k = 0; k < params.size(); ++k) {
      const float saved = params[k];
      params[k] = saved + h;
      const double up = Loss(chain, x, c);
      params[k] = saved - h;
      const double down = Loss(chain, x, c);
      params[k] = saved;
      EXPECT_NEAR(grads[k], (up - down) / (2 * h), 2e-3) << "parameter " << k;
    }
    for (int r = 0; r < 4; ++r) {
      for (int j = 0; j < 3; ++j) {
        MatrixRM moved = x;
        moved(r, j) += h;
        const double up = Loss(chain, moved, c);
        moved(r, j) -= 2 * h;
        const double down = Loss(chain, moved, c);
        EXPECT_NEAR(d_input(r, j), (up - down) / (2 * h), 2e-3) << "input " << r << ", " << j;
      }
    }
  }
}

// Labels that a tiny network can represent exactly (valve 1 open iff x0 > 0.5,
// valve 2 always open): the fit must reach them all and a small loss.
TEST(Distill, LearnsASeparableRule) {
  const std::vector<int> trunk{2, 8}, head{8, 2};
  const int n = 64;
  std::vector<float> params =
      RandomVector(TanhChain::Size(trunk) + TanhChain::Size(head), 4, 0.5f);
  std::vector<float> x(n * 2), y(n * 2);
  std::mt19937 rng(5);
  std::uniform_real_distribution<float> level(0.0f, 1.0f);
  for (int i = 0; i < n; ++i) {
    x[i * 2] = level(rng);
    x[i * 2 + 1] = level(rng);
    y[i * 2] = x[i * 2] > 0.5f ? 1.0f : 0.0f;
    y[i * 2 + 1] = 1.0f;
  }
  const int epochs = 400;
  std::vector<std::int64_t> orders(static_cast<std::size_t>(n) * epochs);
  for (int e = 0; e < epochs; ++e) {
    auto begin = orders.begin() + static_cast<long>(e) * n;
    std::iota(begin, begin + n, 0);
    std::shuffle(begin, begin + n, rng);
  }
  DistillOptions options;
  options.minibatch = 16;
  options.lr = 1e-2;
  const DistillResult r =
      Distill(params.data(), trunk, head, x.data(), y.data(), nullptr, n, orders.data(), epochs,
              options);
  EXPECT_EQ(r.epochs, epochs);
  EXPECT_EQ(r.steps, static_cast<long>(epochs) * (n / 16));
  EXPECT_LT(r.last_loss, 0.1);
  std::vector<float> grads(params.size());
  TanhChain body(trunk, true, params.data(), grads.data());
  TanhChain policy(head, false, params.data() + TanhChain::Size(trunk),
                   grads.data() + TanhChain::Size(trunk));
  MatrixRM xm = Eigen::Map<const MatrixRM>(x.data(), n, 2).array() * 2.0f - 1.0f;
  const MatrixRM logits = policy.Forward(body.Forward(xm));
  for (int i = 0; i < n; ++i) {
    if (std::abs(x[i * 2] - 0.5f) > 0.05f) {  // away from the boundary
      EXPECT_EQ(logits(i, 0) > 0, y[i * 2] > 0.5f) << "row " << i;
    }
    EXPECT_GT(logits(i, 1), 0) << "row " << i;
  }
}

// With one minibatch holding every row, a row given weight 2 is the same
// objective as the row written twice: equal weights after 20 Adam steps up to
// float32 rounding (the sums run over other terms in another order).
TEST(Distill, AWeightIsARepeatedRow) {
  const std::vector<int> trunk{3, 6}, head{6, 2};
  const std::vector<float> start =
      RandomVector(TanhChain::Size(trunk) + TanhChain::Size(head), 6, 0.5f);
  const std::vector<float> x{0.1f, 0.9f, 0.3f, 0.7f, 0.2f, 0.5f, 0.4f, 0.4f, 0.8f};
  const std::vector<float> y{1, 0, 0, 1, 1, 1};
  const std::vector<float> weights{2.0f, 1.0f, 1.0f};
  std::vector<float> x_rep = x, y_rep = y;
  x_rep.insert(x_rep.end(), x.begin(), x.begin() + 3);  // row 0 again
  y_rep.insert(y_rep.end(), y.begin(), y.begin() + 2);
  const int epochs = 20;
  std::vector<std::int64_t> order3, order4;
  for (int e = 0; e < epochs; ++e) {
    order3.insert(order3.end(), {0, 1, 2});
    order4.insert(order4.end(), {0, 1, 2, 3});
  }
  DistillOptions options;
  options.minibatch = 8;
  std::vector<float> weighted = start, repeated = start;
  Distill(weighted.data(), trunk, head, x.data(), y.data(), weights.data(), 3, order3.data(),
          epochs, options);
  Distill(repeated.data(), trunk, head, x_rep.data(), y_rep.data(), nullptr, 4, order4.data(),
          epochs, options);
  for (std::size_t k = 0; k < start.size(); ++k) {
    EXPECT_NE(weighted[k], start[k]) << "parameter " << k << " did not move";
    EXPECT_NEAR(weighted[k], repeated[k], 1e-5) << "parameter " << k;
  }
}

TEST(Distill, StopsAfterAnEpochBelowTheStopLoss) {
  const std::vector<int> trunk{1, 4}, head{4, 1};
  std::vector<float> params = RandomVector(TanhChain::Size(trunk) + TanhChain::Size(head), 7, 0.5f);
  const std::vector<float> x{0.2f, 0.8f}, y{1.0f, 1.0f};
  std::vector<std::int64_t> orders;
  for (int e = 0; e < 1000; ++e) orders.insert(orders.end(), {0, 1});
  DistillOptions options;
  options.lr = 0.05;
  options.stop_loss = 0.05;
  const DistillResult r =
      Distill(params.data(), trunk, head, x.data(), y.data(), nullptr, 2, orders.data(), 1000,
              options);
  EXPECT_LT(r.epochs, 1000);
  EXPECT_GT(r.epochs, 1);
  EXPECT_LT(r.last_loss, 0.05);
}

TEST(Distill, RejectsInconsistentInput) {
  const std::vector<int> trunk{2, 4}, head{4, 1};
  std::vector<float> params(TanhChain::Size(trunk) + TanhChain::Size(head), 0.1f);
  const std::vector<float> x{0.1f, 0.2f}, y{1.0f};
  const std::vector<std::int64_t> bad{1};  // row 1 of 1
  const DistillOptions options;
  EXPECT_THROW(Distill(params.data(), trunk, head, x.data(), y.data(), nullptr, 1, bad.data(), 1,
                       options),
               std::invalid_argument);
  const std::vector<std::int64_t> good{0};
  EXPECT_THROW(Distill(params.data(), trunk, {3, 1}, x.data(), y.data(), nullptr, 1, good.data(),
                       1, options),
               std::invalid_argument);
  EXPECT_THROW(Distill(params.data(), trunk, head, x.data(), y.data(), nullptr, 0, good.data(), 1,
                       options),
               std::invalid_argument);
  EXPECT_THROW(TanhChain({2}, false, params.data(), params.data()), std::invalid_argument);
}

}  // namespace
}  // namespace ftc::learn
