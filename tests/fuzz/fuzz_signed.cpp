// libFuzzer target: the first step of every keyed receiver (the plant, the
// policy node and lcm_echo with --key-file): signing::Verifier::Verify on any
// bytes, then bounded decoding of what it lets through. Properties checked on
// every input:
//   * Verify never crashes or reads out of bounds, whatever the size (ASan);
//   * bytes not signed with the key are refused as a bad signature (a forged
//     MAC of 128 bits is never found by chance);
//   * the input signed with the key verifies once, to exactly its own bytes,
//     and then is refused as a replay; with one byte changed (the position and
//     the flip chosen by the input) it is refused as a bad signature;
//   * the verified payload goes through wire::Decode of every type without
//     crashing (tests/fuzz/wire_harness.h checks each decoder's own properties).
// Built only with -DFTC_FUZZ=ON (scripts/fuzz.sh).
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <string>
#include <vector>

#include "plant/lcm/signing.h"
#include "wire_harness.h"

namespace {

namespace sg = ftc::signing;

const std::string kChannel = "FUZZ_COMMAND";
// a fixed wall clock: the signer's timestamps rise from it by one tick a
// message, so none is ever stale and each is above the last (the verifier's
// floor is 0, not this process's start)
constexpr std::int64_t kNowUs = 1'700'000'000'000'000;

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size > (1u << 16)) return 0;  // an LCM datagram is far smaller
  static const sg::Key key(32, 0x5a);
  static sg::Verifier verifier(key, sg::kDefaultWindowUs, /*not_before_us=*/0);
  static sg::Signer signer(key, 9);

  std::size_t payload = 0;
  if (verifier.Verify(kChannel, data, size, kNowUs, &payload) != sg::Verdict::kBadSignature)
    std::abort();  // unsigned bytes must never pass (nor count as a replay or stale)

  std::vector<unsigned char> signed_msg = signer.Sign(kChannel, data, size, kNowUs);
  if (signed_msg.size() != size + sg::kTrailerBytes) std::abort();
  if (verifier.Verify(kChannel, signed_msg.data(), signed_msg.size(), kNowUs, &payload) !=
          sg::Verdict::kOk ||
      payload != size || (size && std::memcmp(signed_msg.data(), data, size) != 0))
    std::abort();
  if (verifier.Verify(kChannel, signed_msg.data(), signed_msg.size(), kNowUs, &payload) !=
      sg::Verdict::kReplay)
    std::abort();
  // one byte changed anywhere (payload, link id, timestamp or MAC): refused
  const std::size_t at = size ? (data[0] * 257u + size) % signed_msg.size() : 0;
  signed_msg[at] ^= static_cast<unsigned char>(size ? (data[size - 1] | 1u) : 1u);
  if (verifier.Verify(kChannel, signed_msg.data(), signed_msg.size(), kNowUs, &payload) !=
      sg::Verdict::kBadSignature)
    std::abort();

  // what a keyed receiver decodes after the check
  ftc::fuzz::One<ftc::valve_command_t>(data, size);
  ftc::fuzz::One<ftc::plant_control_t>(data, size);
  ftc::fuzz::One<ftc::plant_state_t>(data, size);
  ftc::fuzz::One<ftc::policy_t>(data, size);
  return 0;
}
