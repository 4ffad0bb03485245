// The property every receiver's decoding must keep, for any bytes: the
// libFuzzer targets (fuzz_<type>.cpp, scripts/fuzz.sh) and the short fuzz run
// of the C++ tests (tests/cpp/test_wire.cpp) share it.
//   * wire::Decode never crashes, throws or reads out of bounds (ASan/UBSan
//     in the fuzz build), whatever the declared lengths;
//   * it refuses with a reason, or accepts a buffer that is exactly one
//     message within the schema's bounds: the decoded message re-encodes to
//     the same number of bytes (and to the same bytes for types without
//     booleans, whose wire form is canonical; a string's decoded bytes fill
//     exactly its declared length).
#pragma once

#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <string>
#include <type_traits>
#include <vector>

#include "plant/lcm/wire.h"

namespace ftc::fuzz {

template <typename T>
int One(const std::uint8_t* data, std::size_t size) {
  T msg{};
  std::string why;
  const bool ok = wire::Decode(data, size, &msg, &why);
  if (ok != why.empty()) std::abort();  // a refusal always says why
  if (!ok) return 0;
  if constexpr (std::is_same_v<T, policy_ack_t>) {
    // lcm-gen encodes a string up to its first NUL (strlen): check what was
    // decoded instead, the reason's bytes and its terminator filling the rest
    constexpr std::size_t kFixed = 8 + 8 * 3 + 1 + 8 + 4;
    if (msg.reason.size() + 1 + kFixed != size) std::abort();
    return 0;
  }
  const int n = msg.getEncodedSize();
  if (n != static_cast<int>(size)) std::abort();
  std::vector<std::uint8_t> again(size);
  if (msg.encode(again.data(), 0, n) != n) std::abort();
  // booleans: any non-zero byte is true
  constexpr bool canonical = !std::is_same_v<T, plant_state_t>;
  if (canonical && std::memcmp(again.data(), data, size) != 0) std::abort();
  return 0;
}

}  // namespace ftc::fuzz
