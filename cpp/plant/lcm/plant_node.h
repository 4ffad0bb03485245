// PlantNode: serves one Plant over LCM with the lockstep / real-time protocol.
//
//   controller --valve_command_t--> <prefix>COMMAND --+
//   controller --plant_control_t--> <prefix>CONTROL --+--> PlantNode --> Plant (CVODE core)
//   controllers, recorders   <-- <prefix>STATE <-- plant_state_t <--+
//
// Lockstep mode: every new valve command advances the plant by one 1 s control
// step and is answered by one state carrying the command's seq. A command with
// the seq already applied is a retry: the last state is sent again without
// stepping. Older seqs are stale and ignored. Both are counted in the state.
// Sessions: a controller opens a control session with START or OPEN carrying a
// random 64-bit id; the node follows one session at a time and refuses (and
// counts, other_session) commands and control messages of any other, so a
// neighbour's stray command cannot take the valves. A new session may open
// when none is followed, or when the followed one has sent nothing for
// session_timeout_s (its controller is gone); CLOSE ends one. Sequence numbers
// count within a session. A command repeating the seq just applied with other
// content (two senders in one session) is rejected and counted
// (rejected_commands), so the controller sees it. Every received buffer is checked before decoding
// (plant/lcm/wire.h); refusals are counted and logged rate-limited, never fatal.
// With a key (options.key), every received message must carry a valid MAC
// with a rising timestamp (plant/lcm/signing.h) and every state is signed.
// Real-time mode: the plant steps at rate_hz with zero-order hold on the last
// valid command; a watchdog puts the valves into the safe state when no valid
// command arrives for watchdog_s seconds. The tick after an episode's last
// step starts the next episode and publishes its initial state without
// stepping. A step taken without a command newer than the state before it is
// a missed tick; missed ticks and watchdog trips are counted in every state.
//
// The node owns no process concerns: options parsing and signals stay in the
// app (apps/main.cpp), which hands in the stop predicate. The clock is
// injected so tests can drive the watchdog without sleeping.
#pragma once

#include <lcm/lcm-cpp.hpp>

#include <chrono>
#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include "plant/core/plant.h"
#include "plant/lcm/lcm_bridge.h"
#include "plant/lcm/signing.h"
#include "plant/lcm/wire.h"

namespace ftc {

enum class RunMode { kLockstep, kRealtime };
enum class SafeState { kHold, kClosed };

struct NodeOptions {
  std::string prefix = "FTC_";  // channels <prefix>STATE, <prefix>COMMAND, <prefix>CONTROL
  RunMode mode = RunMode::kLockstep;
  double rate_hz = 10.0;     // real-time mode: control steps per second
  double watchdog_s = 1.0;   // real-time mode: s without a valid command before the safe state
  SafeState safe_state = SafeState::kClosed;  // real-time mode: valves while tripped
  bool verbose = false;      // log watchdog events to stderr
  // s without a message of the followed session after which another session
  // may open (a controller killed without CLOSE leaves its session behind)
  double session_timeout_s = 2.0;
  signing::Key key;  // empty: messages are neither signed nor checked
};

class PlantNode final {
 public:
  using Clock = std::chrono::steady_clock;
  using NowFn = std::function<Clock::time_point()>;

  // Subscribes to the command and control channels of `lcm`; both `lcm` and
  // `plant` must outlive the node. `now` is the node's only clock.
  PlantNode(lcm::LCM* lcm, Plant* plant, const NodeOptions& options, NowFn now = &Clock::now);
  ~PlantNode();  // unsubscribes, so the LCM instance never calls into a dead node
  PlantNode(const PlantNode&) = delete;
  PlantNode& operator=(const PlantNode&) = delete;

  bool shutdown_requested() const { return shutdown_; }
  const LinkCounters& counters() const { return counters_; }

  // Publishes the current state answering the last applied seq (or `command_seq`).
  void PublishState();
  void PublishState(std::int64_t command_seq);

  // Real-time tick: step with the held valves (or the safe state) and publish.
  void Tick(Clock::time_point now);

  // One pass of the serve loop: in real-time mode a tick if one is due (the
  // messages already waiting dispatched first, at most 64; no tick if one of
  // them opened an episode or asked for a shutdown), otherwise waits for at
  // most one message (until the next tick, or 100 ms in lockstep mode so a
  // stop request is seen) and dispatches it. Returns false if LCM's receive
  // failed (a signal interrupting the wait also does).
  bool RunOnce();

  // Calls RunOnce until `stop()` or a SHUTDOWN message. Returns false on an
  // LCM receive failure that was not caused by a stop request.
  bool Run(const std::function<bool()>& stop);

 private:
  bool Admit(std::int64_t seq);
  void OnCommand(const lcm::ReceiveBuffer* rbuf, const std::string& channel);
  void OnControl(const lcm::ReceiveBuffer* rbuf, const std::string& channel);
  void HandleControl(const plant_control_t& msg, const std::string& channel);
  bool SessionIdle() const;
  void RefuseSession(const std::string& what, std::int64_t session, std::int64_t seq);
  void ReportDecodeError(const std::string& channel, std::uint32_t size, const std::string& why);
  // With a key: verifies the trailer and sets *size to the payload's; false
  // (counted) if refused. Without: true.
  bool Authentic(const lcm::ReceiveBuffer* rbuf, const std::string& channel, std::size_t* size);

  lcm::LCM* lcm_;
  Plant* plant_;
  NodeOptions options_;
  NowFn now_;
  Channels channels_;
  Clock::duration period_;  // real-time mode: between ticks
  lcm::Subscription* command_sub_ = nullptr;
  lcm::Subscription* control_sub_ = nullptr;
  LinkCounters counters_;
  wire::RateLimitedLog refusals_{"plant"};
  std::optional<signing::Verifier> verifier_;
  std::optional<signing::Signer> signer_;
  std::int64_t session_ = 0;  // the session followed; 0: none
  std::optional<Clock::time_point> session_heard_;  // its last message
  std::int64_t state_seq_ = 0;
  std::int64_t answered_seq_ = 0;
  // the valves of the command answered_seq_ names, as sent (none: a control message)
  std::optional<std::vector<std::int8_t>> answered_valves_;
  bool shutdown_ = false;
  Valves held_ = Valves::Zero();
  std::optional<Clock::time_point> last_valid_command_time_;
  std::optional<Clock::time_point> next_tick_;  // set by the first RunOnce
  bool watchdog_tripped_;
  bool episode_opened_ = false;  // the last control message handled reset the plant
  bool fresh_command_ = false;  // a valid command arrived since the last published state
  std::int64_t missed_ticks_ = 0;
  std::int64_t watchdog_trips_ = 0;
};

}  // namespace ftc
