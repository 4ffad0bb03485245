// The policy node's forward pass, timed: build/bench_forward WEIGHTS [--passes N]
//
// A weights file (ftc.export) is flown as the node flies it (Policy::Act on a
// History: the layers packed into their diagonal blocks) and, side by side in
// the same run, as one dense chain of its full matrices (learning/tanh_mlp.h),
// each pass "cold" (after 8 MB of other memory was walked, as other processes
// do between two states) and then "warm" (again at once). The order of the
// ways rotates every pass. A third way is the node's between two states: the
// first layer's products of the older steps summed beforehand (Policy::Prepare,
// before the walk), then one step pushed and the policy acted on, timed.
// Prints p50 and p99 in microseconds of each.
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include "learning/tanh_mlp.h"
#include "policy/policy.h"

namespace {

using Clock = std::chrono::steady_clock;

double Quantile(std::vector<double> v, double q) {
  std::sort(v.begin(), v.end());
  return v[static_cast<std::size_t>(q * static_cast<double>(v.size() - 1))];
}

}  // namespace

int main(int argc, char** argv) {
  const char* usage =
      "usage: bench_forward WEIGHTS [--passes N]\n"
      "  times the policy node's forward pass of an exported policy (ftc.export), cold and "
      "warm: dense, packed, and packed with the older steps' first-layer sums prepared as "
      "the node prepares them between two states (N passes each, default 2000)\n";
  if (argc == 2 && (std::string(argv[1]) == "--help" || std::string(argv[1]) == "-h")) {
    std::fputs(usage, stdout);
    return 0;
  }
  if (argc != 2 && !(argc == 4 && std::string(argv[2]) == "--passes")) {
    std::fputs(usage, stderr);
    return 2;
  }
  const int passes = argc == 4 ? std::atoi(argv[3]) : 2000;
  if (passes < 10) {
    std::fprintf(stderr, "bench_forward: --passes must be at least 10\n");
    return 2;
  }
  std::string error;
  auto policy = ftc::policy::Policy::FromFile(argv[1], &error);
  if (!policy) {
    std::fprintf(stderr, "bench_forward: %s\n", error.c_str());
    return 1;
  }
  auto prepared = ftc::policy::Policy::FromFile(argv[1], &error);  // its own sums
  std::vector<float> params = policy->params(), grads(params.size());
  ftc::learn::TanhChain dense(policy->widths(), /*tanh_last=*/false, params.data(), grads.data());
  ftc::learn::MatrixRM input = ftc::learn::MatrixRM::Constant(1, policy->widths().front(), 0.1f);
  ftc::policy::History history;
  history.Start({0.9, 0.8, 0.7, 0.6, 0.5, 0.4});

  std::vector<unsigned char> other(8u << 20, 1);
  auto walk = [&] {
    for (std::size_t i = 0; i < other.size(); i += 64) ++other[i];
  };
  volatile float sink = 0;
  enum Way { kDense, kPacked, kPrepared, kWays };
  // The prepared way's step before the timed pass: its sums, then the push.
  auto step = [&] { history.Push({0.9, 0.8, 0.7, 0.6, 0.5, 0.4}, {1, 0, 1, 0, 1, 0}); };
  auto pass = [&](int way) {
    if (way == kPacked) {
      sink = sink + static_cast<float>(policy->Act(history)[0]);
    } else if (way == kPrepared) {
      sink = sink + static_cast<float>(prepared->Act(history)[0]);
    } else {
      sink = sink + dense.Forward(input)(0, 0);
    }
  };
  std::vector<double> cold[kWays], warm[kWays];
  for (int i = 0; i < passes; ++i) {
    for (int k = 0; k < kWays; ++k) {
      const int way = (i + k) % kWays;
      if (way == kPrepared) prepared->Prepare(history);
      walk();
      if (way == kPrepared) step();
      const auto t0 = Clock::now();
      pass(way);
      const auto t1 = Clock::now();
      if (way == kPrepared) {
        prepared->Prepare(history);
        step();
      }
      const auto t2 = Clock::now();
      pass(way);
      const auto t3 = Clock::now();
      cold[way].push_back(std::chrono::duration<double, std::micro>(t1 - t0).count());
      warm[way].push_back(std::chrono::duration<double, std::micro>(t3 - t2).count());
    }
  }
  std::string widths, blocks;
  for (int w : policy->widths()) widths += (widths.empty() ? "" : "-") + std::to_string(w);
  for (int b : policy->blocks()) blocks += (blocks.empty() ? "" : " ") + std::to_string(b);
  std::printf("bench_forward: %s, window %d, diagonal blocks per layer %s, %d passes each\n",
              widths.c_str(), policy->window(), blocks.c_str(), passes);
  const char* names[kWays] = {"dense", "packed", "prepared"};
  for (int p = 0; p < kWays; ++p)
    std::printf("%-8s cold p50 %.1f us p99 %.1f us | warm p50 %.1f us p99 %.1f us\n", names[p],
                Quantile(cold[p], 0.5), Quantile(cold[p], 0.99), Quantile(warm[p], 0.5),
                Quantile(warm[p], 0.99));
  std::printf("packed / dense: cold p50 %.2f, cold p99 %.2f, warm p50 %.2f\n",
              Quantile(cold[1], 0.5) / Quantile(cold[0], 0.5),
              Quantile(cold[1], 0.99) / Quantile(cold[0], 0.99),
              Quantile(warm[1], 0.5) / Quantile(warm[0], 0.5));
  if (prepared->prepared_acts() == 0) {
    std::printf("prepared: nothing to prepare (a window of 0 or 1, or a first layer of blocks)\n");
  } else {
    std::printf("prepared / packed: cold p50 %.2f, cold p99 %.2f, warm p50 %.2f\n",
                Quantile(cold[2], 0.5) / Quantile(cold[1], 0.5),
                Quantile(cold[2], 0.99) / Quantile(cold[1], 0.99),
                Quantile(warm[2], 0.5) / Quantile(warm[1], 0.5));
  }
  return 0;
}
