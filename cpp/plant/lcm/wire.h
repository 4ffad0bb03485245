// Bounded decoding of the bus's messages: every receiver (the plant, the
// policy node, lcm_echo) checks a buffer's structure before lcm-gen's decoder
// sees it, and never hands it a hostile length.
//
// Why: lcm-gen's C++ decoders resize each array to the count read from the
// wire before checking it against the buffer, and compute the bytes an array
// needs as sizeof(element) * count in an int. So a negative count throws
// std::length_error out of the handler, a policy_t of 36 bytes declaring
// 0x20000001 widths overflows that product and reads past the buffer, and one
// of 40 bytes declaring 250 million params allocates 1 GB. Here each count is
// read from its place in the layout (lcmtypes/ftc/*.lcm, in field order),
// checked against [0, the schema's bound] and against the bytes left, and
// the whole buffer must be exactly what the counts make, all in 64-bit
// arithmetic; only then is the decoder called.
//
// Header-only and free of the plant core: the policy node includes it too.
#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <exception>
#include <iostream>
#include <string>

#include "ftc/plant_control_t.hpp"
#include "ftc/policy_ack_t.hpp"
#include "ftc/plant_state_t.hpp"
#include "ftc/policy_t.hpp"
#include "ftc/valve_command_t.hpp"

namespace ftc::wire {

// Reads big-endian fields (LCM's order) from a buffer, never past its end.
class Reader final {
 public:
  Reader(const void* data, std::size_t size)
      : p_(static_cast<const unsigned char*>(data)), size_(size) {}

  bool Skip(std::uint64_t bytes) {
    if (bytes > size_ - pos_) return false;
    pos_ += static_cast<std::size_t>(bytes);
    return true;
  }
  // Reads an n-byte big-endian integer (n <= 8), sign-extended.
  bool Int(int n, std::int64_t* out) {
    if (static_cast<std::size_t>(n) > size_ - pos_) return false;
    std::uint64_t v = 0;
    for (int i = 0; i < n; ++i) v = (v << 8) | p_[pos_ + static_cast<std::size_t>(i)];
    pos_ += static_cast<std::size_t>(n);
    if (n < 8 && (v >> (8 * n - 1)) & 1u) v |= ~std::uint64_t{0} << (8 * n);
    *out = static_cast<std::int64_t>(v);
    return true;
  }
  std::size_t left() const { return size_ - pos_; }
  std::size_t pos() const { return pos_; }

 private:
  const unsigned char* p_;
  std::size_t size_;
  std::size_t pos_ = 0;
};

// Checks the fingerprint; "" or the reason.
template <typename T>
std::string CheckFingerprint(Reader* r) {
  std::int64_t hash = 0;
  if (!r->Int(8, &hash)) return "shorter than a fingerprint";
  if (hash != T::getHash()) return "not a " + std::string(T::getTypeName()) + " (fingerprint)";
  return {};
}

// Reads an array count of `count_bytes` bytes and checks it against
// [0, bound] and the bytes left for `element_bytes`-byte elements; then skips
// the array. "" or the reason naming the field.
inline std::string Array(Reader* r, const char* name, int count_bytes, std::int64_t bound,
                         int element_bytes, std::int64_t* count) {
  if (!r->Int(count_bytes, count)) return std::string("truncated before ") + name;
  if (*count < 0 || *count > bound)
    return std::string(name) + " is " + std::to_string(*count) + " (allowed: 0.." +
           std::to_string(bound) + ")";
  const std::uint64_t bytes =
      static_cast<std::uint64_t>(*count) * static_cast<std::uint64_t>(element_bytes);
  if (bytes > r->left())
    return std::string(name) + " is " + std::to_string(*count) + ": needs " +
           std::to_string(bytes) + " bytes, " + std::to_string(r->left()) + " left";
  r->Skip(bytes);
  return {};
}

inline std::string Fixed(Reader* r, std::uint64_t bytes, const char* what) {
  return r->Skip(bytes) ? std::string() : std::string("truncated in ") + what;
}

inline std::string End(const Reader& r) {
  return r.left() == 0 ? std::string()
                       : std::to_string(r.left()) + " bytes after the end of the message";
}

constexpr std::int64_t kInt8Max = 127;  // an int8 count's own bound

// The layout of each message, in the field order of lcmtypes/ftc/*.lcm.
inline std::string Check(Reader* r, const valve_command_t*) {
  std::int64_t n = 0;
  std::string why = CheckFingerprint<valve_command_t>(r);
  if (why.empty()) why = Fixed(r, 8 * 4, "utime..state_seq");
  if (why.empty()) why = Array(r, "num_valves", 1, kInt8Max, 1, &n);
  return why.empty() ? End(*r) : why;
}

inline std::string Check(Reader* r, const plant_control_t*) {
  std::string why = CheckFingerprint<plant_control_t>(r);
  if (why.empty()) why = Fixed(r, 8 + 8 + 8 + 1 + 8, "utime..operating_step");
  return why.empty() ? End(*r) : why;
}

inline std::string Check(Reader* r, const plant_state_t*) {
  std::int64_t tanks = 0, engines = 0;
  std::string why = CheckFingerprint<plant_state_t>(r);
  // utime, session, seq, command_seq, episode, step, age, operating_steps
  if (why.empty()) why = Fixed(r, 8 * 4 + 4 + 4 + 8 + 8, "utime..operating_steps");
  if (why.empty() && (!r->Int(1, &tanks) || !r->Int(1, &engines)))
    why = "truncated before num_tanks";
  if (why.empty() && (tanks < 0 || engines < 0))
    why = "num_tanks " + std::to_string(tanks) + ", num_engines " + std::to_string(engines) +
          " (allowed: 0..127)";
  if (why.empty()) {
    // level, true_level (double), valve (int8) per tank; deficit (double) per engine
    const std::uint64_t arrays = static_cast<std::uint64_t>(tanks) * (8 + 8 + 1) +
                                 static_cast<std::uint64_t>(engines) * 8;
    if (!r->Skip(arrays)) why = "num_tanks " + std::to_string(tanks) + ", num_engines " +
                                std::to_string(engines) + ": arrays longer than the message";
  }
  // 4 booleans, 8 link counters, rate_hz, missed_ticks, watchdog_trips
  if (why.empty()) why = Fixed(r, 4 + 8 * 8 + 8 + 8 + 8, "flags..watchdog_trips");
  return why.empty() ? End(*r) : why;
}

inline std::string Check(Reader* r, const policy_t*) {
  std::int64_t widths = 0, params = 0;
  std::string why = CheckFingerprint<policy_t>(r);
  if (why.empty()) why = Fixed(r, 8 + 8, "utime..version");
  if (why.empty()) why = Array(r, "num_widths", 4, policy_t::MAX_WIDTHS, 4, &widths);
  if (why.empty()) why = Array(r, "num_params", 4, policy_t::MAX_PARAMS, 4, &params);
  if (why.empty()) why = Fixed(r, 8, "checksum");
  return why.empty() ? End(*r) : why;
}

inline std::string Check(Reader* r, const policy_ack_t*) {
  std::int64_t length = 0;
  std::string why = CheckFingerprint<policy_ack_t>(r);
  if (why.empty()) why = Fixed(r, 8 * 3 + 1 + 8, "utime..running_version");
  // a string: int32 length counting its NUL, then the bytes
  if (why.empty()) why = Array(r, "reason length", 4, policy_ack_t::MAX_REASON + 1, 1, &length);
  if (why.empty() && length < 1) why = "reason length 0 (no NUL)";
  return why.empty() ? End(*r) : why;
}

// "" if `data` is a well-formed T within the schema's bounds, else the reason.
template <typename T>
std::string Check(const void* data, std::size_t size) {
  Reader r(data, size);
  return Check(&r, static_cast<const T*>(nullptr));
}

// Checks, then decodes into *out. False with the reason in *why for anything
// malformed; never throws, never reads past `size`.
template <typename T>
bool Decode(const void* data, std::size_t size, T* out, std::string* why) {
  *why = Check<T>(data, size);
  if (!why->empty()) return false;
  try {
    if (out->decode(data, 0, static_cast<int>(size)) == static_cast<int>(size)) return true;
    *why = "the decoder refused it";
  } catch (const std::exception& e) {  // not expected after Check: still never fatal
    *why = std::string("the decoder threw: ") + e.what();
  }
  return false;
}

// Logs refused messages without flooding stderr: the first kBurst, then at
// most one line a second saying how many were refused meanwhile.
class RateLimitedLog final {
 public:
  using Clock = std::chrono::steady_clock;
  explicit RateLimitedLog(std::string who) : who_(std::move(who)) {}

  // Counts one refusal; prints `line` if the budget allows.
  void Refused(const std::string& line, Clock::time_point now = Clock::now()) {
    ++total_;
    if (total_ <= kBurst || now - last_ >= std::chrono::seconds(1)) {
      std::cerr << who_ << ": " << line;
      if (suppressed_ > 0) std::cerr << " (" << suppressed_ << " more not logged)";
      std::cerr << "\n";
      suppressed_ = 0;
      last_ = now;
    } else {
      ++suppressed_;
    }
  }
  std::int64_t total() const { return total_; }

 private:
  static constexpr std::int64_t kBurst = 10;
  std::string who_;
  std::int64_t total_ = 0;
  std::int64_t suppressed_ = 0;
  Clock::time_point last_{};
};

}  // namespace ftc::wire
