// Bounded decoding of policy_v2_t, the push that carries a history window, by
// the rules of plant/lcm/wire.h (each count read from its place in the
// layout, checked against the schema's bound and the bytes left, the whole
// buffer exactly what the counts make) before lcm-gen's decoder sees it. It
// lives beside the policy node, its only receiver, and uses wire.h's reader.
#pragma once

#include <cstddef>
#include <exception>
#include <string>

#include "ftc/policy_v2_t.hpp"
#include "plant/lcm/wire.h"

namespace ftc::policy {

// "" if the buffer is a well-formed policy_v2_t within the schema's bounds.
inline std::string CheckPolicyV2(const void* data, std::size_t size) {
  wire::Reader r(data, size);
  std::int64_t widths = 0, params = 0;
  std::string why = wire::CheckFingerprint<policy_v2_t>(&r);
  if (why.empty()) why = wire::Fixed(&r, 8 + 8 + 4 + 1, "utime..stuck_memory");
  if (why.empty()) why = wire::Array(&r, "num_widths", 4, policy_v2_t::MAX_WIDTHS, 4, &widths);
  if (why.empty()) why = wire::Array(&r, "num_params", 4, policy_v2_t::MAX_PARAMS, 4, &params);
  if (why.empty()) why = wire::Fixed(&r, 8, "checksum");
  return why.empty() ? wire::End(r) : why;
}

// True if the buffer starts with policy_v2_t's fingerprint (whatever follows).
inline bool IsPolicyV2(const void* data, std::size_t size) {
  wire::Reader r(data, size);
  return wire::CheckFingerprint<policy_v2_t>(&r).empty();
}

// Checks, then decodes into *out; false with the reason in *why. Never throws.
inline bool DecodePolicyV2(const void* data, std::size_t size, policy_v2_t* out,
                           std::string* why) {
  *why = CheckPolicyV2(data, size);
  if (!why->empty()) return false;
  try {
    if (out->decode(data, 0, static_cast<int>(size)) == static_cast<int>(size)) return true;
    *why = "the decoder refused it";
  } catch (const std::exception& e) {  // not expected after the check: still never fatal
    *why = std::string("the decoder threw: ") + e.what();
  }
  return false;
}

}  // namespace ftc::policy
