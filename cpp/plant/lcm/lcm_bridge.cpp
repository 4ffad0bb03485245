// Message <-> Eigen translation for the plant process (see lcm_bridge.h).
#include "plant/lcm/lcm_bridge.h"

#include <chrono>
#include <cmath>

namespace ftc {

std::int64_t NowMicros() {
  using namespace std::chrono;
  return duration_cast<microseconds>(system_clock::now().time_since_epoch()).count();
}

plant_state_t ToStateMessage(const StepOutcome& outcome, std::int64_t seq, std::int64_t command_seq,
                             std::int64_t operating_steps, const LinkCounters& counters) {
  plant_state_t msg;
  msg.utime = NowMicros();
  msg.seq = seq;
  msg.command_seq = command_seq;
  msg.episode = static_cast<std::int32_t>(outcome.episode);
  msg.step = outcome.step;
  msg.age = outcome.age;
  msg.operating_steps = operating_steps;
  msg.num_tanks = kTanks;
  msg.num_engines = kEngines;
  msg.level.assign(outcome.observed.data(), outcome.observed.data() + kTanks);
  msg.true_level.assign(outcome.level.data(), outcome.level.data() + kTanks);
  msg.valve.resize(kTanks);
  for (int i = 0; i < kTanks; ++i) msg.valve[i] = static_cast<std::int8_t>(outcome.valves[i]);
  msg.deficit.assign(outcome.deficit.data(), outcome.deficit.data() + kEngines);
  msg.terminal = outcome.terminal;
  msg.truncated = outcome.truncated;
  msg.evaluation = outcome.evaluation;
  msg.duplicate_commands = counters.duplicate_commands;
  msg.stale_commands = counters.stale_commands;
  msg.rejected_commands = counters.rejected_commands;
  msg.decode_errors = counters.decode_errors;
  msg.other_session = counters.other_session;
  msg.bad_signature = counters.bad_signature;
  msg.replayed = counters.replayed;
  msg.stale_signed = counters.stale_signed;
  msg.session = 0;  // the node sets the session it follows
  msg.watchdog_tripped = false;
  msg.rate_hz = 0.0;  // lockstep; the real-time node sets these three
  msg.missed_ticks = 0;
  msg.watchdog_trips = 0;
  return msg;
}

bool ValvesFromCommand(const valve_command_t& command, Valves* valves, std::string* reason) {
  if (command.num_valves != kTanks) {
    *reason = "num_valves is " + std::to_string(command.num_valves) + ", expected 6";
    return false;
  }
  for (int i = 0; i < kTanks; ++i) {
    const int v = command.valve[i];
    if (v != 0 && v != 1) {
      *reason = "valve[" + std::to_string(i) + "] is " + std::to_string(v) + ", expected 0 or 1";
      return false;
    }
    (*valves)[i] = v;
  }
  return true;
}

}  // namespace ftc
