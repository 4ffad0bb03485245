// The embedded controller's policy (see policy.h).
#include "policy/policy.h"

#include "learning/tanh_mlp.h"

#include <cmath>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <sstream>

namespace ftc::policy {
namespace {

constexpr std::uint64_t kFnvOffset = 1469598103934665603ull;
constexpr std::uint64_t kFnvPrime = 1099511628211ull;
constexpr int kMaxWidth = 4096;

void Mix(std::uint64_t* h, const void* data, std::size_t n) {
  const auto* bytes = static_cast<const unsigned char*>(data);
  for (std::size_t i = 0; i < n; ++i) {
    *h ^= bytes[i];
    *h *= kFnvPrime;
  }
}

// Little-endian bytes of a 32-bit value (the machine's order may differ).
std::array<unsigned char, 4> Le32(std::uint32_t v) {
  return {static_cast<unsigned char>(v), static_cast<unsigned char>(v >> 8),
          static_cast<unsigned char>(v >> 16), static_cast<unsigned char>(v >> 24)};
}

std::size_t ParamCount(const std::vector<int>& widths) {
  std::size_t n = 0;
  for (std::size_t i = 0; i + 1 < widths.size(); ++i)
    n += static_cast<std::size_t>(widths[i] + 1) * static_cast<std::size_t>(widths[i + 1]);
  return n;
}

}  // namespace

std::uint64_t Checksum(const std::vector<int>& widths, const std::vector<float>& params) {
  std::uint64_t h = kFnvOffset;
  for (int w : widths) {
    const auto b = Le32(static_cast<std::uint32_t>(w));
    Mix(&h, b.data(), b.size());
  }
  for (float p : params) {
    std::uint32_t bits;
    std::memcpy(&bits, &p, sizeof bits);
    const auto b = Le32(bits);
    Mix(&h, b.data(), b.size());
  }
  return h;
}

std::unique_ptr<Policy> Policy::Make(std::vector<int> widths, std::vector<float> params,
                                     std::int64_t version, std::string* error) {
  if (widths.size() < 2 || widths.front() != kTanks || widths.back() != kTanks) {
    *error = "widths must run from 6 (the levels) to 6 (the valves)";
    return nullptr;
  }
  for (int w : widths) {
    if (w < 1 || w > kMaxWidth) {
      *error = "a layer width of " + std::to_string(w) + " (allowed: 1.." +
               std::to_string(kMaxWidth) + ")";
      return nullptr;
    }
  }
  if (params.size() != ParamCount(widths)) {
    *error = std::to_string(params.size()) + " parameters for layers that take " +
             std::to_string(ParamCount(widths));
    return nullptr;
  }
  for (std::size_t i = 0; i < params.size(); ++i) {
    if (!std::isfinite(params[i])) {
      *error = "parameter " + std::to_string(i) + " is not finite";
      return nullptr;
    }
  }
  return std::unique_ptr<Policy>(new Policy(std::move(widths), std::move(params), version));
}

struct Policy::Net {
  Net(const std::vector<int>& widths, std::vector<float>* params)
      : grads(params->size()), chain(widths, /*tanh_last=*/false, params->data(), grads.data()),
        input(1, kTanks) {}
  std::vector<float> grads;  // the chain's gradient buffer: unused when acting
  learn::TanhChain chain;
  learn::MatrixRM input;
};

Policy::Policy(std::vector<int> widths, std::vector<float> params, std::int64_t version)
    : widths_(std::move(widths)),
      params_(std::move(params)),
      version_(version),
      net_(std::make_unique<Net>(widths_, &params_)) {}

Policy::~Policy() = default;

std::array<std::int8_t, kTanks> Policy::Act(const std::array<double, kTanks>& level) {
  for (int i = 0; i < kTanks; ++i) net_->input(0, i) = static_cast<float>(2.0 * level[i] - 1.0);
  const auto& logits = net_->chain.Forward(net_->input);
  std::array<std::int8_t, kTanks> u{};
  for (int i = 0; i < kTanks; ++i) u[i] = logits(0, i) > 0.0f ? 1 : 0;
  return u;
}

std::unique_ptr<Policy> Policy::FromFile(const std::string& path, std::string* error) {
  std::ifstream in(path);
  if (!in) {
    *error = path + ": cannot open the weights file";
    return nullptr;
  }
  auto fail = [&](int line, const std::string& why) {
    *error = path + ":" + std::to_string(line) + ": " + why;
    return nullptr;
  };
  std::string text, word;
  int line = 0;
  std::vector<int> widths;
  std::vector<float> params;
  std::int64_t version = 0;
  std::size_t expected = 0;
  bool have_checksum = false;
  std::uint64_t checksum = 0;
  while (std::getline(in, text)) {
    ++line;
    if (text.empty() || text[0] == '#') continue;
    std::istringstream fields(text);
    fields >> word;
    if (line == 1) {
      int format = 0;
      if (word != "ftc-policy" || !(fields >> format) || format != 1)
        return fail(line, "not an ftc-policy 1 weights file (first line: 'ftc-policy 1')");
    } else if (word == "version") {
      if (!(fields >> version)) return fail(line, "version: an integer expected");
    } else if (word == "widths") {
      int w;
      while (fields >> w) widths.push_back(w);
      if (widths.empty()) return fail(line, "widths: integers expected");
    } else if (word == "params") {
      if (!(fields >> expected)) return fail(line, "params: a count expected");
    } else if (word == "checksum") {
      std::string hex;
      char* end = nullptr;
      if (fields >> hex) checksum = std::strtoull(hex.c_str(), &end, 16);
      if (hex.empty() || end == nullptr || *end != '\0')
        return fail(line, "checksum: 16 hex digits expected");
      have_checksum = true;
    } else {
      std::istringstream values(text);
      double v;
      while (values >> v) params.push_back(static_cast<float>(v));
      if (!values.eof()) return fail(line, "a number expected: '" + text.substr(0, 40) + "'");
    }
  }
  if (line == 0) return fail(1, "empty file");
  if (params.size() != expected)
    return fail(line, "params says " + std::to_string(expected) + " values, the file holds " +
                          std::to_string(params.size()) + " (truncated?)");
  if (!have_checksum) return fail(line, "no checksum line");
  if (Checksum(widths, params) != checksum)
    return fail(line, "checksum mismatch: the weights were changed or truncated");
  std::string why;
  auto policy = Make(std::move(widths), std::move(params), version, &why);
  if (!policy) return fail(line, why);
  return policy;
}

}  // namespace ftc::policy
