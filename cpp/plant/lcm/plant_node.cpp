// The plant's LCM protocol node (see plant_node.h).
#include "plant/lcm/plant_node.h"

#include <iostream>
#include <utility>

namespace ftc {
namespace {

// LCM keeps at most 30 undispatched messages per subscription by default; a
// burst beyond that (retries, a flood of garbage) would be dropped silently
// instead of answered or counted. Bounded, so a flood cannot exhaust memory.
constexpr int kQueueCapacity = 10000;  // messages per subscription
// Longest wait for a message in lockstep mode: bounds the reaction time to a
// stop request (a signal).
constexpr int kMaxWaitMs = 100;
// Messages already waiting that a due tick dispatches first (real-time mode):
// enough for any controller's backlog after the node was descheduled, few
// enough that a neighbour flooding the bus cannot hold the tick back.
constexpr int kMaxBacklogPerTick = 64;

}  // namespace

PlantNode::PlantNode(lcm::LCM* lcm, Plant* plant, const NodeOptions& options, NowFn now)
    : lcm_(lcm),
      plant_(plant),
      options_(options),
      now_(std::move(now)),
      channels_(options.prefix),
      period_(std::chrono::duration_cast<Clock::duration>(
          std::chrono::duration<double>(1.0 / options.rate_hz))),
      // In real-time mode the valves are in the safe state until a first command.
      watchdog_tripped_(options.mode == RunMode::kRealtime) {
  command_sub_ = lcm_->subscribe(channels_.command, &PlantNode::OnCommand, this);
  control_sub_ = lcm_->subscribe(channels_.control, &PlantNode::OnControl, this);
  for (auto* sub : {command_sub_, control_sub_}) sub->setQueueCapacity(kQueueCapacity);
  if (!options_.key.empty()) {
    verifier_.emplace(options_.key);
    signer_.emplace(options_.key, /*link_id=*/0);
  }
}

PlantNode::~PlantNode() {
  lcm_->unsubscribe(control_sub_);
  lcm_->unsubscribe(command_sub_);
}

void PlantNode::PublishState() { PublishState(answered_seq_); }

void PlantNode::PublishState(std::int64_t command_seq) {
  auto msg = ToStateMessage(plant_->last(), ++state_seq_, command_seq, plant_->operating_steps(),
                            counters_);
  msg.watchdog_tripped = watchdog_tripped_;
  msg.session = session_;
  if (options_.mode == RunMode::kRealtime) {
    msg.rate_hz = options_.rate_hz;
    msg.missed_ticks = missed_ticks_;
    msg.watchdog_trips = watchdog_trips_;
  }
  if (!signer_) {
    lcm_->publish(channels_.state, &msg);
    return;
  }
  std::vector<unsigned char> buf(static_cast<std::size_t>(msg.getEncodedSize()));
  msg.encode(buf.data(), 0, static_cast<int>(buf.size()));
  const auto signed_msg = signer_->Sign(channels_.state, buf.data(), buf.size(), NowMicros());
  lcm_->publish(channels_.state, signed_msg.data(), static_cast<unsigned>(signed_msg.size()));
}

bool PlantNode::Authentic(const lcm::ReceiveBuffer* rbuf, const std::string& channel,
                          std::size_t* size) {
  *size = rbuf->data_size;
  if (!verifier_) return true;
  const auto verdict = verifier_->Verify(channel, rbuf->data, rbuf->data_size, NowMicros(), size);
  if (verdict == signing::Verdict::kOk) return true;
  ++(verdict == signing::Verdict::kBadSignature ? counters_.bad_signature
     : verdict == signing::Verdict::kReplay     ? counters_.replayed
                                                 : counters_.stale_signed);
  refusals_.Refused("refused a message on " + channel + " (" +
                    std::to_string(rbuf->data_size) + " bytes): " + signing::Describe(verdict));
  return false;
}

void PlantNode::Tick(Clock::time_point now) {
  const bool stale = !last_valid_command_time_ ||
                     now - *last_valid_command_time_ >
                         std::chrono::duration<double>(options_.watchdog_s);
  if (stale && !watchdog_tripped_) {
    ++watchdog_trips_;
    if (options_.verbose)
      std::cerr << "plant: watchdog: no valid command for " << options_.watchdog_s
                << " s, valves to safe state\n";
  }
  watchdog_tripped_ = stale;
  if (plant_->episode_over()) {
    // The next episode starts here, and its first step waits for a command
    // answering its initial state (not the one sent for the last episode's end).
    if (plant_->last().evaluation) {
      plant_->ResetEvaluation();
    } else {
      plant_->Reset();
    }
  } else {
    if (!fresh_command_) ++missed_ticks_;
    Valves u = held_;
    if (watchdog_tripped_ && options_.safe_state == SafeState::kClosed) u.setZero();
    plant_->Step(u);
  }
  fresh_command_ = false;  // the next step needs a command answering this state
  PublishState();
}

bool PlantNode::RunOnce() {
  int timeout_ms = kMaxWaitMs;
  if (options_.mode == RunMode::kRealtime) {
    const auto now = now_();
    if (!next_tick_) next_tick_ = now + period_;
    if (now >= *next_tick_) {
      // What arrived before the tick was due is answered by it: after the node
      // was descheduled (a busy machine), the commands waiting in its socket
      // are the controller's latest, and the watchdog must not trip on a
      // silence that was the node's own.
      episode_opened_ = false;
      for (int k = 0; k < kMaxBacklogPerTick; ++k) {
        const int handled = lcm_->handleTimeout(0);
        if (handled < 0) return false;
        if (handled == 0 || shutdown_ || episode_opened_) break;
      }
      if (shutdown_) return true;  // its answer was the last state
      if (episode_opened_) {
        // The waiting message opened an episode and its first state went out
        // just now: the controller gets a whole period to answer it, as when
        // the message comes between two ticks.
        next_tick_ = now + period_;
        return true;
      }
      Tick(now);
      *next_tick_ += period_;
      if (*next_tick_ < now) next_tick_ = now + period_;  // fell behind: do not burst
      return true;
    }
    timeout_ms = static_cast<int>(
        std::chrono::duration_cast<std::chrono::milliseconds>(*next_tick_ - now).count());
  }
  return lcm_->handleTimeout(timeout_ms) >= 0;
}

bool PlantNode::Run(const std::function<bool()>& stop) {
  while (!stop() && !shutdown_) {
    // A signal interrupts the wait (EINTR): that is a stop, not a failure.
    if (!RunOnce() && !stop()) return false;
  }
  return true;
}

// Sequence rules shared by commands and control messages. Returns true if the
// message is new and should be acted upon.
bool PlantNode::Admit(std::int64_t seq) {
  if (seq == answered_seq_ && answered_seq_ != 0) {
    ++counters_.duplicate_commands;
    if (options_.mode == RunMode::kLockstep) PublishState();  // lost answer: re-send
    return false;
  }
  if (seq < answered_seq_) {
    ++counters_.stale_commands;
    return false;
  }
  return true;
}

void PlantNode::OnCommand(const lcm::ReceiveBuffer* rbuf, const std::string& channel) {
  valve_command_t cmd{};
  std::string why;
  std::size_t size = 0;
  if (!Authentic(rbuf, channel, &size)) return;
  if (!wire::Decode(rbuf->data, size, &cmd, &why)) {
    ReportDecodeError(channel, rbuf->data_size, why);
    return;
  }
  if (session_ == 0 || cmd.session != session_) {
    RefuseSession("command", cmd.session, cmd.seq);
    return;
  }
  session_heard_ = now_();
  if (cmd.seq == answered_seq_ && answered_seq_ != 0 &&
      (!answered_valves_ || cmd.valve != *answered_valves_)) {
    // The seq just applied again, with other content: two senders in one session
    // (a neighbour that read the session off the bus raced the controller). Not
    // applied; counted where the controller sees it (rejected_commands).
    ++counters_.rejected_commands;
    refusals_.Refused("rejected command seq " + std::to_string(cmd.seq) + " on " + channel +
                      ": it repeats the seq of the " +
                      (answered_valves_ ? "command" : "control message") +
                      " applied with other content (another sender in session " +
                      std::to_string(session_) + ")");
    if (options_.mode == RunMode::kLockstep) PublishState();  // the sender learns of it now
    return;
  }
  if (!Admit(cmd.seq)) return;
  Valves u;
  std::string reason;
  if (!ValvesFromCommand(cmd, &u, &reason)) {
    ++counters_.rejected_commands;
    refusals_.Refused("rejected command seq " + std::to_string(cmd.seq) + " on " + channel +
                      ": " + reason);
    return;
  }
  answered_seq_ = cmd.seq;
  answered_valves_ = cmd.valve;
  if (options_.mode == RunMode::kLockstep) {
    plant_->Step(u);
    PublishState();
  } else {
    held_ = u;
    last_valid_command_time_ = now_();
    fresh_command_ = true;
  }
}

void PlantNode::OnControl(const lcm::ReceiveBuffer* rbuf, const std::string& channel) {
  plant_control_t msg{};  // zeroed: GCC cannot see that decode fills it
  std::string why;
  std::size_t size = 0;
  if (!Authentic(rbuf, channel, &size)) return;
  if (!wire::Decode(rbuf->data, size, &msg, &why)) {
    ReportDecodeError(channel, rbuf->data_size, why);
    return;
  }
  HandleControl(msg, channel);
}

bool PlantNode::SessionIdle() const {
  return session_ == 0 || !session_heard_ ||
         now_() - *session_heard_ > std::chrono::duration<double>(options_.session_timeout_s);
}

void PlantNode::HandleControl(const plant_control_t& msg, const std::string& channel) {
  if (msg.command == plant_control_t::HELLO) {
    // A handshake is answered whatever its session and seq (so a new client
    // can attach) and changes nothing, so a repeated HELLO is harmless.
    PublishState(msg.seq);
    return;
  }
  const bool opens = msg.command == plant_control_t::START || msg.command == plant_control_t::OPEN;
  if (session_ == 0 || msg.session != session_) {
    if (opens && msg.session != 0 && SessionIdle()) {
      session_ = msg.session;  // a new session: its seq counts from here
      answered_seq_ = 0;
      answered_valves_.reset();
      fresh_command_ = false;
      if (options_.verbose)
        std::cerr << "plant: following session " << session_ << " (" << channel << ")\n";
    } else if (!(msg.command == plant_control_t::SHUTDOWN && session_ == 0 && msg.session == 0)) {
      // (a SHUTDOWN without a session is obeyed only while nobody is in control)
      RefuseSession(std::string("control ") + std::to_string(static_cast<int>(msg.command)),
                    msg.session, msg.seq);
      return;
    }
  }
  session_heard_ = now_();
  if (!Admit(msg.seq)) {
    // A control message sent again (its answer was lost): in real-time mode
    // too it gets one, the current state (lockstep's Admit re-sent it already).
    if (options_.mode == RunMode::kRealtime && msg.seq == answered_seq_) PublishState();
    return;
  }
  switch (msg.command) {
    case plant_control_t::RESET:
      plant_->Reset();
      break;
    case plant_control_t::EVALUATE:
      plant_->ResetEvaluation();
      break;
    case plant_control_t::SHUTDOWN:
      shutdown_ = true;
      break;
    case plant_control_t::OPEN:
    case plant_control_t::CLOSE:
      break;
    case plant_control_t::START:
      // the command line's --start-step bound: the step counter and the age
      // computed from it stay far from overflow
      if (msg.operating_step < 0 || msg.operating_step > plant_control_t::MAX_OPERATING_STEP) {
        ++counters_.rejected_commands;
        refusals_.Refused("rejected START seq " + std::to_string(msg.seq) + ": operating_step " +
                          std::to_string(msg.operating_step) + " is outside 0.." +
                          std::to_string(plant_control_t::MAX_OPERATING_STEP));
        return;
      }
      plant_->SetOperatingSteps(msg.operating_step);
      plant_->Reset();
      break;
    default:
      ++counters_.rejected_commands;
      refusals_.Refused("rejected control seq " + std::to_string(msg.seq) + ": unknown command " +
                        std::to_string(static_cast<int>(msg.command)));
      return;
  }
  episode_opened_ = msg.command == plant_control_t::RESET ||
                    msg.command == plant_control_t::EVALUATE ||
                    msg.command == plant_control_t::START;
  answered_seq_ = msg.seq;
  answered_valves_.reset();  // the seq of a control message
  fresh_command_ = false;  // a new episode: its first step needs a command answering it
  PublishState();
  if (msg.command == plant_control_t::CLOSE) {
    session_ = 0;
    session_heard_.reset();
  }
}

void PlantNode::RefuseSession(const std::string& what, std::int64_t session, std::int64_t seq) {
  ++counters_.other_session;
  refusals_.Refused("refused " + what + " seq " + std::to_string(seq) + " of session " +
                    std::to_string(session) + ": following " +
                    (session_ == 0 ? std::string("no session (open one with START or OPEN)")
                                   : "session " + std::to_string(session_)) +
                    "; counted (" + std::to_string(counters_.other_session) + " so far)");
}

void PlantNode::ReportDecodeError(const std::string& channel, std::uint32_t size,
                                  const std::string& why) {
  ++counters_.decode_errors;
  refusals_.Refused("undecodable message on " + channel + " (" + std::to_string(size) +
                    " bytes): " + why + "; counted (" + std::to_string(counters_.decode_errors) +
                    " so far)");
}

}  // namespace ftc
