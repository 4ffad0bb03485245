// libFuzzer target: the plant's message decoding (what OnCommand and OnControl
// run on every received buffer) and its command validation; each type's own
// target is fuzz_<type>.cpp. Properties checked on every input:
//   * decoding never crashes, throws or reads out of bounds (ASan/UBSan);
//   * a buffer that decodes fully re-encodes to the same bytes (these two
//     types have no booleans, so the wire form is canonical);
//   * ValvesFromCommand accepts exactly six valves in {0, 1} and otherwise
//     gives a reason.
// Built only with -DFTC_FUZZ=ON (scripts/fuzz.sh).
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <string>
#include <vector>

#include "plant/lcm/lcm_bridge.h"
#include "plant/lcm/wire.h"

namespace {

template <typename T>
void CheckRoundTrip(const std::uint8_t* data, std::size_t size, const T& msg) {
  const int n = msg.getEncodedSize();
  if (n != static_cast<int>(size)) std::abort();
  std::vector<std::uint8_t> again(size);
  if (msg.encode(again.data(), 0, n) != n) std::abort();
  if (std::memcmp(again.data(), data, size) != 0) std::abort();
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size > (1u << 16)) return 0;  // an LCM datagram is far smaller
  std::string why;
  ftc::valve_command_t cmd;
  if (ftc::wire::Decode(data, size, &cmd, &why)) {
    CheckRoundTrip(data, size, cmd);
    ftc::Valves u = ftc::Valves::Constant(-1);
    std::string reason;
    const bool ok = ftc::ValvesFromCommand(cmd, &u, &reason);
    bool valid = cmd.num_valves == ftc::kTanks;
    for (int i = 0; valid && i < ftc::kTanks; ++i) valid = cmd.valve[i] == 0 || cmd.valve[i] == 1;
    if (ok != valid) std::abort();
    if (ok && (u.minCoeff() < 0 || u.maxCoeff() > 1)) std::abort();
    if (!ok && reason.empty()) std::abort();
  }

  ftc::plant_control_t control{};
  if (ftc::wire::Decode(data, size, &control, &why)) CheckRoundTrip(data, size, control);

  // The controller side decodes states; the C++ decoder must be as robust.
  ftc::plant_state_t state;
  (void)ftc::wire::Decode(data, size, &state, &why);
  return 0;
}
