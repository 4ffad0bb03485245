// The embedded controller's policy (see policy.h).
#include "policy/policy.h"

#include "learning/tanh_mlp.h"

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <numeric>
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

std::uint64_t Checksum(const std::vector<int>& widths, const std::vector<float>& params,
                       int window, bool stuck_memory) {
  std::uint64_t h = Checksum(widths, params);  // FNV-1a continues from its state
  const auto b = Le32(static_cast<std::uint32_t>(window));
  Mix(&h, b.data(), b.size());
  if (stuck_memory) {
    const auto one = Le32(1u);
    Mix(&h, one.data(), one.size());
  }
  return h;
}

History::History() : slots_(static_cast<std::size_t>(kMaxWindow) * kStepFeatures, 0.0f) {
  Forget();
}

void History::Scale(const std::array<double, kTanks>& level, float* out) {
  for (int i = 0; i < kTanks; ++i) {
    // float32 first, then clip and 2 x - 1 in float32: NumPy's roundings
    const float x = std::min(std::max(static_cast<float>(level[i]), 0.0f), 1.0f);
    out[i] = 2.0f * x - 1.0f;
  }
}

void History::Start(const std::array<double, kTanks>& level) {
  float step[kStepFeatures];
  Scale(level, step);
  for (int i = kTanks; i < kStepFeatures; ++i) step[i] = -1.0f;  // closed
  for (int k = 0; k < kMaxWindow; ++k)
    std::copy(step, step + kStepFeatures, slots_.data() + k * kStepFeatures);
  newest_ = 0;
  level_ = level;
}

void History::Push(const std::array<double, kTanks>& level,
                   const std::array<std::int8_t, kTanks>& valves,
                   const std::array<std::int8_t, kTanks>& applied) {
  newest_ = (newest_ + kMaxWindow - 1) % kMaxWindow;  // the oldest slot becomes the newest
  float* step = slots_.data() + newest_ * kStepFeatures;
  Scale(level, step);
  for (int i = 0; i < kTanks; ++i) step[kTanks + i] = valves[i] ? 1.0f : -1.0f;
  level_ = level;
  for (int i = 0; i < kTanks; ++i) {
    const bool commanded = valves[i] != 0, held = applied[i] != 0;
    if (commanded == held) continue;  // followed its command: says nothing
    stuck_[i] = commanded ? 1.0f : -1.0f;           // stuck closed
    stuck_[kTanks + i] = commanded ? -1.0f : 1.0f;  // stuck open
  }
}

void History::Newest(int window, float* out) const {
  for (int k = 0; k < window; ++k) {
    const float* step = slots_.data() + ((newest_ + k) % kMaxWindow) * kStepFeatures;
    std::copy(step, step + kStepFeatures, out + k * kStepFeatures);
  }
}

std::unique_ptr<Policy> Policy::Make(int window, std::vector<int> widths,
                                     std::vector<float> params, std::int64_t version,
                                     std::string* error, bool stuck_memory) {
  if (window < 0 || window > kMaxWindow) {
    *error = "a window of " + std::to_string(window) + " steps (allowed: 0.." +
             std::to_string(kMaxWindow) + ")";
    return nullptr;
  }
  if (stuck_memory && window == 0) {
    *error = "the stuck memory is read after a history window (window 0 given)";
    return nullptr;
  }
  const int input = InputWidth(window, stuck_memory);
  if (widths.size() < 2 || widths.front() != input ||
      (widths.back() != kTanks && widths.back() != kSettings)) {
    *error = "widths must run from " + std::to_string(input) +
             (window == 0 ? " (the levels)"
                          : " (a window of " + std::to_string(window) +
                                " steps of levels and valves" +
                                (stuck_memory ? ", then the stuck memory)" : ")")) +
             " to 6 (a logit per valve) or 64 (a logit per valve setting)";
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
  return std::unique_ptr<Policy>(
      new Policy(window, std::move(widths), std::move(params), version, stuck_memory));
}

// The layers as they are flown: each layer's weights split into the blocks of
// its block-diagonal structure, packed. A dense layer is one block. The
// members of an ensemble (python/ftc/learning/history_policy.py: ensemble)
// are such blocks in every layer between the first and the last: flown dense,
// two thirds of a three-member student's middle layer would be zeros read
// from memory and multiplied (0.9 MB of weights against 0.5 MB packed), and a
// forward pass after other processes evicted the cache is bound by those reads.
// Skipping exact zeros changes no product; the order of the sums within a
// block is Eigen's, as for the dense layer.
struct Policy::Net {
  struct Layer {
    int in = 0, out = 0, blocks = 1;
    std::vector<learn::MatrixRM> w;  // blocks x (in / blocks, out / blocks)
    Eigen::RowVectorXf b;
    Eigen::RowVectorXf z;  // the layer's output
  };

  Net(const std::vector<int>& widths, const std::vector<float>& params)
      : input(learn::MatrixRM::Zero(1, widths.front())) {
    std::size_t offset = 0;
    for (std::size_t l = 0; l + 1 < widths.size(); ++l) {
      Layer layer;
      layer.in = widths[l];
      layer.out = widths[l + 1];
      const float* w = params.data() + offset;  // (in, out) row-major, then b
      layer.blocks = DiagonalBlocks(w, layer.in, layer.out);
      const int bi = layer.in / layer.blocks, bo = layer.out / layer.blocks;
      for (int k = 0; k < layer.blocks; ++k) {
        learn::MatrixRM block(bi, bo);
        for (int r = 0; r < bi; ++r)
          for (int c = 0; c < bo; ++c)
            block(r, c) = w[static_cast<std::size_t>(k * bi + r) * layer.out + k * bo + c];
        layer.w.push_back(std::move(block));
      }
      offset += static_cast<std::size_t>(layer.in) * layer.out;
      layer.b = Eigen::Map<const Eigen::RowVectorXf>(params.data() + offset, layer.out);
      offset += layer.out;
      layer.z.resize(layer.out);
      layers.push_back(std::move(layer));
    }
  }

  // The most blocks K (dividing both widths) such that every weight outside
  // the K diagonal blocks of the (in, out) matrix is exactly zero; 1 if none.
  static int DiagonalBlocks(const float* w, int in, int out) {
    for (int k = std::gcd(in, out); k > 1; --k) {
      if (in % k != 0 || out % k != 0) continue;
      const int bi = in / k, bo = out / k;
      bool diagonal = true;
      for (int r = 0; r < in && diagonal; ++r)
        for (int c = 0; c < out; ++c)
          if (r / bi != c / bo && w[static_cast<std::size_t>(r) * out + c] != 0.0f) {
            diagonal = false;
            break;
          }
      if (diagonal) return k;
    }
    return 1;
  }

  // The logits of `input`: tanh after every layer but the last.
  const Eigen::RowVectorXf& Forward() {
    Layer& first = layers.front();
    const int bi = first.in / first.blocks, bo = first.out / first.blocks;
    for (int k = 0; k < first.blocks; ++k)
      first.z.segment(k * bo, bo).noalias() =
          Eigen::Map<const Eigen::RowVectorXf>(input.data() + k * bi, bi) * first.w[k];
    return Rest();
  }

  // The same, the first layer's rows of the window's older steps (slots 1..W-1)
  // read from Prepare's sums.
  const Eigen::RowVectorXf& ForwardPrepared() {
    Layer& first = layers.front();
    const learn::MatrixRM& w = first.w[0];
    const Eigen::Map<const Eigen::RowVectorXf> x(input.data(), first.in);
    first.z = partial;
    first.z.noalias() += x.head(kStepFeatures) * w.topRows(kStepFeatures);
    const int tail = first.in - kStepFeatures - static_cast<int>(older.size());
    if (tail > 0) first.z.noalias() += x.tail(tail) * w.bottomRows(tail);  // the stuck memory
    return Rest();
  }

  // Sums the first layer's products of `history`'s slots 0..W-2, which become
  // slots 1..W-1 after the next push (a dense first layer).
  void Prepare(const History& history, int window) {
    older.resize(static_cast<std::size_t>(kStepFeatures * (window - 1)));
    history.Newest(window - 1, older.data());
    partial.noalias() =
        Eigen::Map<const Eigen::RowVectorXf>(older.data(), static_cast<Eigen::Index>(older.size())) *
        layers.front().w[0].middleRows(kStepFeatures, static_cast<Eigen::Index>(older.size()));
    has_partial = true;
  }

  // The first layer's bias and tanh, then every other layer (tanh after all but the last).
  const Eigen::RowVectorXf& Rest() {
    for (std::size_t l = 0; l < layers.size(); ++l) {
      Layer& layer = layers[l];
      if (l > 0) {
        const float* x = layers[l - 1].z.data();
        const int bi = layer.in / layer.blocks, bo = layer.out / layer.blocks;
        for (int k = 0; k < layer.blocks; ++k)
          layer.z.segment(k * bo, bo).noalias() =
              Eigen::Map<const Eigen::RowVectorXf>(x + k * bi, bi) * layer.w[k];
      }
      layer.z += layer.b;
      if (l + 1 < layers.size()) layer.z = layer.z.array().tanh().matrix();
    }
    return layers.back().z;
  }

  std::vector<Layer> layers;
  learn::MatrixRM input;
  // Prepare's sums, and the steps they were taken of (the next window's slots 1..W-1)
  Eigen::RowVectorXf partial;
  bool has_partial = false;
  std::vector<float> older;
};

Policy::Policy(int window, std::vector<int> widths, std::vector<float> params,
               std::int64_t version, bool stuck_memory)
    : window_(window),
      stuck_memory_(stuck_memory),
      widths_(std::move(widths)),
      params_(std::move(params)),
      version_(version),
      net_(std::make_unique<Net>(widths_, params_)) {}

Policy::~Policy() = default;

std::vector<int> Policy::blocks() const {
  std::vector<int> k;
  for (const auto& layer : net_->layers) k.push_back(layer.blocks);
  return k;
}

std::array<std::int8_t, kTanks> Policy::Act(const std::array<double, kTanks>& level) {
  if (window_ != 0) {  // the first step of an episode
    History history;
    history.Start(level);
    return Act(history);
  }
  for (int i = 0; i < kTanks; ++i) net_->input(0, i) = static_cast<float>(2.0 * level[i] - 1.0);
  return Decide();
}

std::array<std::int8_t, kTanks> Policy::Act(const History& history) {
  if (window_ == 0) return Act(history.level());
  history.Newest(window_, net_->input.data());  // row-major (1, 12 W): the slots in order
  if (stuck_memory_) history.Memory(net_->input.data() + kStepFeatures * window_);
  Net& net = *net_;
  const bool prepared =
      net.has_partial && std::memcmp(net.input.data() + kStepFeatures, net.older.data(),
                                     net.older.size() * sizeof(float)) == 0;
  prepared_acts_ += prepared;
  return Decide(prepared);
}

bool Policy::Preparable() const {
  return window_ > 1 && net_->layers.front().blocks == 1;
}

void Policy::Prepare(const History& history) {
  if (Preparable()) net_->Prepare(history, window_);
}

void Policy::Warm() {
  if (net_->has_partial)
    net_->ForwardPrepared();
  else
    net_->Forward();
}

std::array<std::int8_t, kTanks> Policy::Decide(bool prepared) {
  const auto& logits = prepared ? net_->ForwardPrepared() : net_->Forward();
  if (widths_.back() == kSettings) return JointValves(logits.data());
  std::array<std::int8_t, kTanks> u{};
  for (int i = 0; i < kTanks; ++i) u[i] = logits[i] > 0.0f ? 1 : 0;
  return u;
}

std::array<std::int8_t, kTanks> Policy::JointValves(const float* logits) {
  int best = 0;
  for (int a = 1; a < kSettings; ++a)
    if (logits[a] > logits[best]) best = a;  // strictly: a tie keeps the first
  std::array<std::int8_t, kTanks> u{};
  for (int i = 0; i < kTanks; ++i) u[i] = (best >> i) & 1;
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
  int format = 0, window = 0, stuck_memory = 0;
  bool have_window = false;
  std::size_t expected = 0;
  bool have_checksum = false;
  std::uint64_t checksum = 0;
  while (std::getline(in, text)) {
    ++line;
    if (text.empty() || text[0] == '#') continue;
    std::istringstream fields(text);
    fields >> word;
    if (line == 1) {
      if (word != "ftc-policy" || !(fields >> format) || (format != 1 && format != 2))
        return fail(line, "not an ftc-policy weights file (first line: 'ftc-policy 1' or "
                          "'ftc-policy 2')");
    } else if (word == "window" && format == 2) {
      if (!(fields >> window)) return fail(line, "window: an integer expected");
      have_window = true;
    } else if (word == "stuck_memory" && format == 2) {
      if (!(fields >> stuck_memory) || (stuck_memory != 0 && stuck_memory != 1))
        return fail(line, "stuck_memory: 0 or 1 expected");
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
  if (format == 2 && !have_window) return fail(line, "no window line (ftc-policy 2 needs one)");
  if ((format == 2 ? Checksum(widths, params, window, stuck_memory == 1)
                   : Checksum(widths, params)) != checksum)
    return fail(line, "checksum mismatch: the weights were changed or truncated");
  std::string why;
  auto policy = Make(window, std::move(widths), std::move(params), version, &why,
                     stuck_memory == 1);
  if (!policy) return fail(line, why);
  return policy;
}

}  // namespace ftc::policy
