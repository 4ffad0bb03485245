// Translation between LCM messages and the plant core's Eigen types. The only
// place that knows both sides: the physics never sees an LCM type.
#pragma once

#include <cstdint>
#include <string>

#include "ftc/plant_control_t.hpp"
#include "ftc/plant_state_t.hpp"
#include "ftc/valve_command_t.hpp"
#include "plant/core/plant.h"

namespace ftc {

// Channel names: <prefix> + suffix.
struct Channels {
  explicit Channels(const std::string& prefix)
      : state(prefix + "STATE"), command(prefix + "COMMAND"), control(prefix + "CONTROL") {}
  std::string state;    // plant -> controllers: plant_state_t
  std::string command;  // controller -> plant: valve_command_t
  std::string control;  // controller -> plant: plant_control_t
};

// Link-health counters published in every state.
struct LinkCounters {
  std::int64_t duplicate_commands = 0;
  std::int64_t stale_commands = 0;
  std::int64_t rejected_commands = 0;
  std::int64_t decode_errors = 0;
  std::int64_t other_session = 0;  // commands and control messages of a session not followed
  std::int64_t bad_signature = 0;  // with a key: bad or missing MAC
  std::int64_t replayed = 0;       // with a key: timestamp not above the link's last
  std::int64_t stale_signed = 0;   // with a key: timestamp older than the window
};

std::int64_t NowMicros();

plant_state_t ToStateMessage(const StepOutcome& outcome, std::int64_t seq, std::int64_t command_seq,
                             std::int64_t operating_steps, const LinkCounters& counters);

// Validates a command; on success writes the valves and returns true, else
// writes the reason and returns false.
bool ValvesFromCommand(const valve_command_t& command, Valves* valves, std::string* reason);

}  // namespace ftc
