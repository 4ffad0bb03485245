// The deterministic policy of the embedded controller: the exported actor
// (levels -> 2 x - 1 -> dense tanh layers -> 6 logits; a valve opens where its
// logit is positive), read from the weights file ftc.export writes or from a
// pushed policy_t, checked whole before use. No LCM in here, and no Eigen in
// this header: the arithmetic (learning/tanh_mlp.h) is compiled with the
// learning kernels' flags (-march=native), whose Eigen types must not meet
// those of code compiled without them.
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>


namespace ftc::policy {

constexpr int kTanks = 6;

// FNV-1a 64 of the widths (int32 little-endian) then the params (float32
// little-endian): the checksum of the weights file and of policy_t.
std::uint64_t Checksum(const std::vector<int>& widths, const std::vector<float>& params);

class Policy {
 public:
  // A policy of these widths and params, or null with the reason in *error:
  // widths must run 6 -> ... -> 6 with every width in 1..4096, params must
  // hold exactly their weights and biases, every value finite.
  static std::unique_ptr<Policy> Make(std::vector<int> widths, std::vector<float> params,
                                      std::int64_t version, std::string* error);

  // Reads the weights file (the format of docs/deploy.md); null with the reason
  // (naming the file and line) in *error.
  static std::unique_ptr<Policy> FromFile(const std::string& path, std::string* error);

  // Valve commands (0/1) for tank levels in metres.
  std::array<std::int8_t, kTanks> Act(const std::array<double, kTanks>& level);

  ~Policy();
  std::int64_t version() const { return version_; }
  const std::vector<int>& widths() const { return widths_; }

 private:
  Policy(std::vector<int> widths, std::vector<float> params, std::int64_t version);

  struct Net;  // the layers (policy.cpp)
  std::vector<int> widths_;
  std::vector<float> params_;
  std::int64_t version_;
  std::unique_ptr<Net> net_;
};

}  // namespace ftc::policy
