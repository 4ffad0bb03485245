// Seeded normal vectors for the learning kernels' tests.
#pragma once

#include <random>
#include <vector>

namespace ftc::learn {

inline std::vector<float> RandomVector(std::size_t n, unsigned seed, float scale) {
  std::mt19937 rng(seed);
  std::normal_distribution<float> normal(0.0f, scale);
  std::vector<float> v(n);
  for (float& x : v) x = normal(rng);
  return v;
}

}  // namespace ftc::learn
