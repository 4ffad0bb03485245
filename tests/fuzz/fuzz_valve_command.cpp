// libFuzzer target: bounded decoding of valve_command_t (tests/fuzz/wire_harness.h).
// Built only with -DFTC_FUZZ=ON (scripts/fuzz.sh).
#include "wire_harness.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  return ftc::fuzz::One<ftc::valve_command_t>(data, size);
}
