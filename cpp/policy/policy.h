// The deterministic policy of the embedded controller: the exported actor
// (its input -> dense tanh layers -> its head), read from the weights file ftc.export writes or from a pushed
// policy_t / policy_v2_t, checked whole before use. Its input is either the
// newest levels mapped to 2 x - 1 (window 0: the PPO policies) or a window of
// the last W steps of levels and valve commands (the adaptive student,
// python/ftc/learning/history_policy.py), kept by History, optionally followed
// by History's stuck memory (the valves seen applied otherwise than
// commanded). No LCM in here,
// and no Eigen in this header: the arithmetic (learning/tanh_mlp.h) is
// compiled with the learning kernels' flags (-march=native), whose Eigen
// types must not meet those of code compiled without them.
//
// The head is told by the last layer's width: 6 logits (the valves head:
// valve i opens where logit i is positive) or 64 (the joint head, one logit
// per valve setting: the setting a of the largest logit, the first on ties as
// torch's argmax, opens valve i iff bit i of a is set).
#pragma once

#include <array>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>


namespace ftc::policy {

constexpr int kTanks = 6;
constexpr int kStepFeatures = 2 * kTanks;  // one step of history: levels, then valves
constexpr int kSettings = 1 << kTanks;     // the joint head's outputs: one per valve setting
// The longest window a policy may read (policy_v2_t::MAX_WINDOW); History keeps
// this many steps whatever the flying policy reads, so a pushed policy with
// another window finds the episode's history as it would have kept it.
constexpr int kMaxWindow = 256;

// FNV-1a 64 of the widths (int32 little-endian) then the params (float32
// little-endian): the checksum of an ftc-policy 1 weights file and of policy_t.
std::uint64_t Checksum(const std::vector<int>& widths, const std::vector<float>& params);

// The same, continued with the window (int32 little-endian), then for a
// policy that reads the stuck memory with the int32 1: the checksum of an
// ftc-policy 2 weights file and of policy_v2_t.
std::uint64_t Checksum(const std::vector<int>& widths, const std::vector<float>& params,
                       int window, bool stuck_memory = false);

// The stuck memory's width: per valve, seen stuck closed, then seen stuck open.
constexpr int kStuckFeatures = 2 * kTanks;

// The input width of a policy reading `window` steps (0: the levels alone),
// and the stuck memory after them if it reads it.
inline int InputWidth(int window, bool stuck_memory = false) {
  return (window == 0 ? kTanks : kStepFeatures * window) + (stuck_memory ? kStuckFeatures : 0);
}

// The last kMaxWindow steps an episode went through, as the adaptive student's
// HistoryWindow keeps them for one plant: slot k holds the levels acted on k
// steps ago and the valves commanded on the step that led to them (closed for
// the episode's first levels), each clipped to [0, 1] and mapped to 2 x - 1 in
// float32 (the same roundings as NumPy's float32 arithmetic there). Its stuck
// memory holds, per valve, whether it was last seen stuck closed (applied
// closed when commanded open) or stuck open (applied open when commanded
// closed), 1 or -1; it outlives episodes (a plant's valves stay stuck) until
// Forget.
class History final {
 public:
  History();

  // An episode begins at `level`: every slot holds these levels, valves closed.
  void Start(const std::array<double, kTanks>& level);

  // After commanding `valves` the plant published `level`: it becomes slot 0.
  void Push(const std::array<double, kTanks>& level,
            const std::array<std::int8_t, kTanks>& valves) {
    Push(level, valves, valves);
  }

  // The same, the plant having applied `applied` (its state message's valves):
  // a valve applied otherwise than commanded enters the stuck memory.
  void Push(const std::array<double, kTanks>& level,
            const std::array<std::int8_t, kTanks>& valves,
            const std::array<std::int8_t, kTanks>& applied);

  // Clears the stuck memory (another plant).
  void Forget() { stuck_.fill(-1.0f); }

  // The stuck memory, kStuckFeatures floats of +-1, into out.
  void Memory(float* out) const { std::copy(stuck_.begin(), stuck_.end(), out); }

  // The newest `window` slots (1..kMaxWindow), newest first, into out
  // (kStepFeatures x window floats): the student's input.
  void Newest(int window, float* out) const;

  // The levels of slot 0, in metres, as published.
  const std::array<double, kTanks>& level() const { return level_; }

 private:
  static void Scale(const std::array<double, kTanks>& level, float* out);

  std::vector<float> slots_;  // kMaxWindow x kStepFeatures, a ring
  int newest_ = 0;            // the ring index of slot 0
  std::array<double, kTanks> level_{};
  std::array<float, kStuckFeatures> stuck_;
};

class Policy {
 public:
  // A policy of this window, widths and params, or null with the reason in
  // *error: window must be in 0..kMaxWindow, widths must run InputWidth(window,
  // stuck_memory) -> ... -> 6 or 64 (the head) with every width in 1..4096,
  // params must hold exactly their weights and biases, every value finite; a
  // policy that reads the stuck memory needs a window.
  static std::unique_ptr<Policy> Make(int window, std::vector<int> widths,
                                      std::vector<float> params, std::int64_t version,
                                      std::string* error, bool stuck_memory = false);
  // The same with window 0 (a policy of the levels).
  static std::unique_ptr<Policy> Make(std::vector<int> widths, std::vector<float> params,
                                      std::int64_t version, std::string* error) {
    return Make(0, std::move(widths), std::move(params), version, error);
  }

  // Reads the weights file (the format of docs/deploy.md: ftc-policy 1, or 2
  // with a window); null with the reason (naming the file and line) in *error.
  static std::unique_ptr<Policy> FromFile(const std::string& path, std::string* error);

  // Valve commands (0/1) for tank levels in metres (a policy of window 0).
  std::array<std::int8_t, kTanks> Act(const std::array<double, kTanks>& level);

  // Valve commands (0/1) for the history: its newest `window()` steps (and
  // its stuck memory if the policy reads it), or its newest levels for window 0.
  std::array<std::int8_t, kTanks> Act(const History& history);

  // Between two states: sums the first layer's products of the steps the
  // next Act will read from this history once one more step is pushed (its
  // slots 0..W-2, then 1..W-1), so that Act then multiplies the new step and
  // the stuck memory alone, off the weights of the other W-1 steps (with the
  // default student, 11 of its first layer's 13 parts: 0.38 of its packed
  // weights' bytes). Act uses the sums only where its window's slots 1..W-1
  // are bit for bit the steps they were taken of (whatever history it is
  // given), else it runs the whole layer. The sums are taken in another order
  // than the whole layer's: the logits move by float32 roundings (~1e-6 of
  // their terms), as between any two BLAS kernels. A policy of window 0 or 1,
  // or with a first layer of several blocks, has nothing to prepare.
  void Prepare(const History& history);

  // Runs the pass the next Act will run, on whatever input the last one left,
  // its result dropped: the weights that pass reads (with Prepare's sums, the
  // first layer's rows of the new step and of the stuck memory, and the layers
  // after it) come into the cache.
  void Warm();

  // How many Acts used Prepare's sums.
  std::int64_t prepared_acts() const { return prepared_acts_; }

  // The valves of the joint head's kSettings logits: the bits of the first
  // largest one's index (valve i open iff bit i is set).
  static std::array<std::int8_t, kTanks> JointValves(const float* logits);

  ~Policy();
  std::int64_t version() const { return version_; }
  int window() const { return window_; }
  bool stuck_memory() const { return stuck_memory_; }
  const std::vector<int>& widths() const { return widths_; }
  // Per layer, the diagonal blocks it is flown as (1: dense; K: an ensemble
  // of K members' layer, the zeros between them skipped).
  std::vector<int> blocks() const;
  // The weights as loaded: each layer's W (in, out) row-major, then its b.
  const std::vector<float>& params() const { return params_; }

 private:
  Policy(int window, std::vector<int> widths, std::vector<float> params, std::int64_t version,
         bool stuck_memory);
  std::array<std::int8_t, kTanks> Decide(bool prepared = false);
  bool Preparable() const;

  struct Net;  // the layers (policy.cpp)
  int window_;
  bool stuck_memory_;
  std::vector<int> widths_;
  std::vector<float> params_;
  std::int64_t version_;
  std::unique_ptr<Net> net_;
  std::int64_t prepared_acts_ = 0;
};

}  // namespace ftc::policy
