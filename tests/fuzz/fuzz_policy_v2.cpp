// libFuzzer target: bounded decoding of policy_v2_t, the policy node's push
// with a history window (cpp/policy/push_wire.h), and the node's choice
// between the two push types. Properties checked on every input:
//   * DecodePolicyV2 never crashes, throws or reads out of bounds (ASan/UBSan),
//     whatever the declared lengths;
//   * it refuses with a reason, or accepts a buffer that is exactly one
//     message within the schema's bounds, which re-encodes to the same bytes
//     (no booleans: the wire form is canonical);
//   * a buffer accepted as policy_v2_t is never also a policy_t (the
//     fingerprints tell them apart).
// Built only with -DFTC_FUZZ=ON (scripts/fuzz.sh).
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <string>
#include <vector>

#include "policy/push_wire.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  ftc::policy_v2_t msg{};
  std::string why;
  const bool ok = ftc::policy::DecodePolicyV2(data, size, &msg, &why);
  if (ok != why.empty()) std::abort();  // a refusal always says why
  if (ok && !ftc::policy::IsPolicyV2(data, size)) std::abort();
  if (!ok) return 0;
  if (msg.num_widths < 0 || msg.num_widths > ftc::policy_v2_t::MAX_WIDTHS ||
      msg.num_params < 0 || msg.num_params > ftc::policy_v2_t::MAX_PARAMS)
    std::abort();
  const int n = msg.getEncodedSize();
  if (n != static_cast<int>(size)) std::abort();
  std::vector<std::uint8_t> again(size);
  if (msg.encode(again.data(), 0, n) != n) std::abort();
  if (std::memcmp(again.data(), data, size) != 0) std::abort();
  ftc::policy_t v1{};
  if (ftc::wire::Decode(data, size, &v1, &why)) std::abort();
  return 0;
}
