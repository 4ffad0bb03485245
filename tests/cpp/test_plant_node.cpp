// PlantNode's protocol (sessions, lockstep answers, retries, stale and
// duplicate messages, the real-time watchdog, shutdown) on memq://, with a
// fake clock. Every test but the session tests runs in a session the fixture
// opens (OPEN, seq 0).
//
// memq:// in LCM 1.5.3: one in-process queue per lcm instance, one message
// dispatched per handle() call, and a publish to a channel nobody subscribes
// to is dropped. The node and the test share the instance: a message the test
// publishes reaches the node's handler on the next handle(); the state it
// publishes in answer reaches the test's handler on the one after.
#include <gtest/gtest.h>

#include <lcm/lcm-cpp.hpp>

#include <chrono>
#include <cstdint>
#include <functional>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "plant/core/plant.h"
#include "plant/lcm/lcm_bridge.h"
#include "plant/lcm/plant_node.h"

namespace ftc {
namespace {

using std::chrono::milliseconds;

const std::vector<std::int8_t> kAllOpen{1, 1, 1, 1, 1, 1};
const std::vector<std::int8_t> kAllClosed{0, 0, 0, 0, 0, 0};

class PlantNodeTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_TRUE(lcm_.good());
    lcm_.subscribe(channels_.state, &PlantNodeTest::OnState, this);
  }

  void StartNode(RunMode mode, SafeState safe_state = SafeState::kClosed, bool open = true) {
    NodeOptions options;
    options.prefix = kPrefix;
    options.mode = mode;
    options.rate_hz = 10.0;
    options.watchdog_s = 1.0;
    options.safe_state = safe_state;
    options.session_timeout_s = 2.0;
    node_ = std::make_unique<PlantNode>(&lcm_, &plant_, options, [this] { return now_; });
    if (open) {
      SendControl(0, plant_control_t::OPEN);
      Drain();
      states_.clear();
    }
  }

  void SendCommand(std::int64_t seq, const std::vector<std::int8_t>& valves,
                   std::int64_t session = kSession) {
    valve_command_t cmd;
    cmd.utime = 0;
    cmd.session = session;
    cmd.seq = seq;
    cmd.state_seq = 0;
    cmd.num_valves = static_cast<std::int8_t>(valves.size());
    cmd.valve = valves;
    lcm_.publish(channels_.command, &cmd);
  }

  void SendControl(std::int64_t seq, std::int8_t command, std::int64_t operating_step = 0,
                   std::int64_t session = kSession) {
    plant_control_t msg;
    msg.utime = 0;
    msg.session = session;
    msg.seq = seq;
    msg.command = command;
    msg.operating_step = operating_step;
    lcm_.publish(channels_.control, &msg);
  }

  // Dispatches everything queued: messages to the node, its answers to states_.
  void Drain() {
    while (lcm_.handleTimeout(0) > 0) {
    }
  }

  // Sends one message, dispatches, and returns the states it produced.
  std::vector<plant_state_t> Exchange(const std::function<void()>& send) {
    const std::size_t before = states_.size();
    send();
    Drain();
    return {states_.begin() + static_cast<std::ptrdiff_t>(before), states_.end()};
  }

  // Exchange for a message that must be answered by exactly one state.
  plant_state_t ExchangeOne(const std::function<void()>& send) {
    const auto answers = Exchange(send);
    EXPECT_EQ(answers.size(), 1u);
    return answers.empty() ? plant_state_t{} : answers.back();
  }

  static constexpr const char* kPrefix = "TEST_";
  static constexpr std::int64_t kSession = 0x5e55104a5e55104a;
  static constexpr std::int64_t kOther = -77;
  lcm::LCM lcm_{"memq://"};
  Channels channels_{kPrefix};
  Plant plant_{FaultScenario{}, 0};
  PlantNode::Clock::time_point now_{std::chrono::hours(1)};  // the node's clock
  std::vector<plant_state_t> states_;
  std::unique_ptr<PlantNode> node_;  // last: goes before the lcm and plant it uses

 private:
  void OnState(const lcm::ReceiveBuffer*, const std::string&, const plant_state_t* msg) {
    states_.push_back(*msg);
  }
};

TEST_F(PlantNodeTest, LockstepCommandStepsOnceAndIsAnsweredWithItsSeq) {
  StartNode(RunMode::kLockstep);
  const plant_state_t initial = ExchangeOne([&] { node_->PublishState(); });
  EXPECT_EQ(initial.seq, 2);  // the first answered the fixture's OPEN
  EXPECT_EQ(initial.session, kSession);
  EXPECT_EQ(initial.command_seq, 0);
  EXPECT_EQ(initial.step, 0);

  const plant_state_t first = ExchangeOne([&] { SendCommand(1, kAllOpen); });
  EXPECT_EQ(first.seq, 3);
  EXPECT_EQ(first.session, kSession);
  EXPECT_EQ(first.command_seq, 1);
  EXPECT_EQ(first.step, 1);
  EXPECT_EQ(first.operating_steps, 1);
  EXPECT_EQ(first.valve, kAllOpen);
  EXPECT_NE(first.true_level, initial.true_level);  // it did step

  const plant_state_t second = ExchangeOne([&] { SendCommand(2, kAllClosed); });
  EXPECT_EQ(second.command_seq, 2);
  EXPECT_EQ(second.step, 2);
  EXPECT_EQ(second.valve, kAllClosed);
  EXPECT_EQ(plant_.operating_steps(), 2);
  EXPECT_EQ(second.duplicate_commands + second.stale_commands +
                second.rejected_commands + second.decode_errors,
            0);
}

TEST_F(PlantNodeTest, RetryResendsTheLastStateWithoutStepping) {
  StartNode(RunMode::kLockstep);
  const plant_state_t answer = ExchangeOne([&] { SendCommand(1, kAllOpen); });
  EXPECT_EQ(answer.duplicate_commands, 0);

  const plant_state_t retry = ExchangeOne([&] { SendCommand(1, kAllOpen); });
  EXPECT_EQ(retry.seq, answer.seq + 1);
  EXPECT_EQ(retry.command_seq, 1);
  EXPECT_EQ(retry.step, 1);
  EXPECT_EQ(retry.true_level, answer.true_level);
  EXPECT_EQ(retry.duplicate_commands, 1);
  EXPECT_EQ(plant_.operating_steps(), 1);
}

TEST_F(PlantNodeTest, ARepeatOfTheAppliedSeqWithOtherValvesIsRejectedAndCounted) {
  // two senders in one session (a neighbour raced the controller with its seq):
  // the second command is neither applied nor taken for a retry, and the plant's
  // answer counts it where the controller looks (rejected_commands)
  StartNode(RunMode::kLockstep);
  const plant_state_t first = ExchangeOne([&] { SendCommand(1, kAllOpen); });
  const plant_state_t raced = ExchangeOne([&] { SendCommand(1, kAllClosed); });
  EXPECT_EQ(raced.command_seq, 1);
  EXPECT_EQ(raced.step, 1);
  EXPECT_EQ(raced.true_level, first.true_level);
  EXPECT_EQ(raced.rejected_commands, 1);
  EXPECT_EQ(raced.duplicate_commands, 0);
  EXPECT_EQ(plant_.operating_steps(), 1);
  // the same valves again: a retry, as before
  const plant_state_t retry = ExchangeOne([&] { SendCommand(1, kAllOpen); });
  EXPECT_EQ(retry.duplicate_commands, 1);
  EXPECT_EQ(retry.rejected_commands, 1);
  // a command with the seq of the control message just applied: another sender too
  ExchangeOne([&] { SendControl(2, plant_control_t::RESET); });
  const plant_state_t after_reset = ExchangeOne([&] { SendCommand(2, kAllOpen); });
  EXPECT_EQ(after_reset.rejected_commands, 2);
  EXPECT_EQ(after_reset.step, 0);
}

TEST_F(PlantNodeTest, StaleSeqIsIgnoredAndCounted) {
  StartNode(RunMode::kLockstep);
  ExchangeOne([&] { SendCommand(5, kAllOpen); });

  EXPECT_TRUE(Exchange([&] { SendCommand(3, kAllClosed); }).empty());
  EXPECT_EQ(plant_.operating_steps(), 1);
  EXPECT_EQ(node_->counters().stale_commands, 1);

  const plant_state_t next = ExchangeOne([&] { SendCommand(6, kAllClosed); });
  EXPECT_EQ(next.command_seq, 6);
  EXPECT_EQ(next.step, 2);
  EXPECT_EQ(next.stale_commands, 1);
  EXPECT_EQ(next.duplicate_commands, 0);
}

TEST_F(PlantNodeTest, DuplicateResetResetsOnceAndResendsItsAnswer) {
  StartNode(RunMode::kLockstep);
  ExchangeOne([&] { SendCommand(1, kAllOpen); });

  const plant_state_t reset = ExchangeOne([&] { SendControl(2, plant_control_t::RESET); });
  EXPECT_EQ(reset.command_seq, 2);
  EXPECT_EQ(reset.episode, 1);
  EXPECT_EQ(reset.step, 0);

  const plant_state_t duplicate = ExchangeOne([&] { SendControl(2, plant_control_t::RESET); });
  EXPECT_EQ(duplicate.command_seq, 2);
  EXPECT_EQ(duplicate.episode, 1);  // a second Reset would make it 2
  EXPECT_EQ(duplicate.duplicate_commands, 1);
}

TEST_F(PlantNodeTest, HelloIsAnsweredWithItsSeqEveryTimeAndChangesNothing) {
  StartNode(RunMode::kLockstep);
  ExchangeOne([&] { SendCommand(4, kAllOpen); });
  for (int k = 0; k < 2; ++k) {
    const plant_state_t hello = ExchangeOne([&] { SendControl(100, plant_control_t::HELLO); });
    EXPECT_EQ(hello.command_seq, 100);
    EXPECT_EQ(hello.step, 1);
    EXPECT_EQ(hello.duplicate_commands, 0);
  }
  // The HELLO's seq was not taken as applied: seq 5 is new, not stale.
  const plant_state_t next = ExchangeOne([&] { SendCommand(5, kAllOpen); });
  EXPECT_EQ(next.step, 2);
  EXPECT_EQ(next.stale_commands, 0);
}

TEST_F(PlantNodeTest, InvalidAndUndecodableMessagesAreCountedNotApplied) {
  StartNode(RunMode::kLockstep);
  EXPECT_TRUE(Exchange([&] { SendCommand(1, {1, 1, 2, 0, 0, 0}); }).empty());
  EXPECT_TRUE(Exchange([&] { SendCommand(2, {1, 1, 1}); }).empty());
  EXPECT_TRUE(Exchange([&] { SendControl(3, 42); }).empty());
  const std::string garbage = "not an LCM message";
  EXPECT_TRUE(Exchange([&] {
                lcm_.publish(channels_.command, garbage.data(),
                             static_cast<unsigned>(garbage.size()));
              }).empty());
  // A valve command on the control channel: wrong fingerprint.
  EXPECT_TRUE(Exchange([&] {
                valve_command_t cmd;
                cmd.utime = 0;
                cmd.session = kSession;
                cmd.seq = 4;
                cmd.state_seq = 0;
                cmd.num_valves = 6;
                cmd.valve = kAllOpen;
                lcm_.publish(channels_.control, &cmd);
              }).empty());
  EXPECT_EQ(plant_.operating_steps(), 0);

  // A rejected seq is not taken as applied: the same seq, valid, steps.
  const plant_state_t valid = ExchangeOne([&] { SendCommand(1, kAllOpen); });
  EXPECT_EQ(valid.step, 1);
  EXPECT_EQ(valid.rejected_commands, 3);
  EXPECT_EQ(valid.decode_errors, 2);
  EXPECT_EQ(valid.duplicate_commands, 0);
}

TEST_F(PlantNodeTest, RealtimeStartsInTheSafeState) {
  StartNode(RunMode::kRealtime);
  const plant_state_t tick = ExchangeOne([&] { node_->Tick(now_); });
  EXPECT_TRUE(tick.watchdog_tripped);
  EXPECT_EQ(tick.valve, kAllClosed);
  EXPECT_EQ(tick.command_seq, 0);
  EXPECT_EQ(tick.step, 1);
}

TEST_F(PlantNodeTest, RealtimeWatchdogClosesTheValvesAfterTheTimeout) {
  StartNode(RunMode::kRealtime, SafeState::kClosed);
  const auto t0 = now_;
  SendCommand(1, kAllOpen);
  ASSERT_TRUE(node_->RunOnce());  // before the first tick (t0 + 100 ms): takes the command
  Drain();
  EXPECT_TRUE(states_.empty());  // real-time mode answers with ticks, not per command
  EXPECT_EQ(plant_.operating_steps(), 0);

  const auto tick_at = [&](milliseconds t) {
    now_ = t0 + t;
    return ExchangeOne([&] { ASSERT_TRUE(node_->RunOnce()); });
  };
  const plant_state_t held = tick_at(milliseconds(100));
  EXPECT_FALSE(held.watchdog_tripped);
  EXPECT_EQ(held.valve, kAllOpen);
  EXPECT_EQ(held.command_seq, 1);

  const plant_state_t at_limit = tick_at(milliseconds(1000));  // exactly --watchdog: valid
  EXPECT_FALSE(at_limit.watchdog_tripped);
  EXPECT_EQ(at_limit.valve, kAllOpen);

  const plant_state_t tripped = tick_at(milliseconds(1100));
  EXPECT_TRUE(tripped.watchdog_tripped);
  EXPECT_EQ(tripped.valve, kAllClosed);

  // A new valid command clears it at the next tick.
  now_ = t0 + milliseconds(1150);
  SendCommand(2, kAllOpen);
  ASSERT_TRUE(node_->RunOnce());
  const plant_state_t recovered = tick_at(milliseconds(1200));
  EXPECT_FALSE(recovered.watchdog_tripped);
  EXPECT_EQ(recovered.valve, kAllOpen);
  EXPECT_EQ(recovered.command_seq, 2);
}

TEST_F(PlantNodeTest, RealtimeHoldSafeStateKeepsTheLastValves) {
  StartNode(RunMode::kRealtime, SafeState::kHold);
  SendCommand(1, kAllOpen);
  ASSERT_TRUE(node_->RunOnce());
  now_ += milliseconds(1500);
  const plant_state_t tripped = ExchangeOne([&] { ASSERT_TRUE(node_->RunOnce()); });
  EXPECT_TRUE(tripped.watchdog_tripped);
  EXPECT_EQ(tripped.valve, kAllOpen);
}

// A node descheduled past --watchdog while the controller kept sending: the
// command waiting in its socket when the tick is due is applied by that tick,
// and the watchdog does not trip on the node's own silence.
TEST_F(PlantNodeTest, RealtimeTickAppliesTheCommandWaitingForItBeforeTheWatchdog) {
  StartNode(RunMode::kRealtime, SafeState::kHold);
  SendCommand(1, kAllOpen);
  ASSERT_TRUE(node_->RunOnce());
  now_ += milliseconds(1500);  // beyond --watchdog (1 s) since command 1
  const plant_state_t tick = ExchangeOne([&] {
    SendCommand(2, kAllClosed);  // queued, not yet dispatched, when the tick is due
    ASSERT_TRUE(node_->RunOnce());
  });
  EXPECT_FALSE(tick.watchdog_tripped);
  EXPECT_EQ(tick.valve, kAllClosed);
  EXPECT_EQ(tick.command_seq, 2);
  EXPECT_EQ(tick.watchdog_trips, 0);
}

// A RESET waiting when the tick is due opens the episode and is answered
// with its first state; that state is not stepped at once with the old
// valves: the controller gets a period to answer it.
TEST_F(PlantNodeTest, RealtimeResetWaitingForATickIsAnsweredBeforeTheNextStep) {
  StartNode(RunMode::kRealtime, SafeState::kHold);
  SendCommand(1, kAllOpen);
  ASSERT_TRUE(node_->RunOnce());  // sets the first tick at now + 100 ms
  now_ += milliseconds(100);
  ASSERT_EQ(ExchangeOne([&] { ASSERT_TRUE(node_->RunOnce()); }).step, 1);
  now_ += milliseconds(100);
  const plant_state_t opened = ExchangeOne([&] {
    SendControl(2, plant_control_t::RESET);  // waiting when the tick is due
    ASSERT_TRUE(node_->RunOnce());
  });
  EXPECT_EQ(opened.step, 0);
  EXPECT_EQ(opened.command_seq, 2);
  now_ += milliseconds(50);  // within the period: nothing
  EXPECT_TRUE(Exchange([&] { ASSERT_TRUE(node_->RunOnce()); }).empty());
  SendCommand(3, kAllClosed);
  ASSERT_TRUE(node_->RunOnce());
  now_ += milliseconds(50);  // a period after the reset: its first step
  const plant_state_t first = ExchangeOne([&] { ASSERT_TRUE(node_->RunOnce()); });
  EXPECT_EQ(first.step, 1);
  EXPECT_EQ(first.valve, kAllClosed);
  EXPECT_EQ(first.missed_ticks, 0);
}

// A SHUTDOWN waiting when the tick is due ends the node on its answer: no
// later message is applied and no step is taken after it.
TEST_F(PlantNodeTest, RealtimeShutdownWaitingForATickIsTheLastState) {
  StartNode(RunMode::kRealtime);
  ASSERT_TRUE(node_->RunOnce());  // sets the first tick at now + 100 ms
  now_ += milliseconds(100);
  SendControl(1, plant_control_t::SHUTDOWN);
  SendCommand(2, kAllOpen);
  ASSERT_TRUE(node_->RunOnce());
  EXPECT_TRUE(node_->shutdown_requested());
  Drain();
  ASSERT_EQ(states_.size(), 1u);
  EXPECT_EQ(states_[0].command_seq, 1);
  EXPECT_EQ(plant_.operating_steps(), 0);
}

TEST_F(PlantNodeTest, RealtimeRetryIsCountedButNotAnswered) {
  StartNode(RunMode::kRealtime);
  SendCommand(1, kAllOpen);
  SendCommand(1, kAllOpen);
  ASSERT_TRUE(node_->RunOnce());
  ASSERT_TRUE(node_->RunOnce());
  Drain();
  EXPECT_TRUE(states_.empty());
  EXPECT_EQ(node_->counters().duplicate_commands, 1);
}

TEST_F(PlantNodeTest, RealtimeCountsStepsTakenWithoutAFreshCommandAndWatchdogTrips) {
  StartNode(RunMode::kRealtime);
  const auto tick = [&] { return ExchangeOne([&] { node_->Tick(now_); }); };
  const plant_state_t unanswered = tick();  // nobody commands yet: a missed tick
  EXPECT_EQ(unanswered.missed_ticks, 1);
  EXPECT_EQ(unanswered.watchdog_trips, 0);  // safe from the start: not a trip
  EXPECT_DOUBLE_EQ(unanswered.rate_hz, 10.0);

  Exchange([&] { SendCommand(1, kAllOpen); });
  now_ += milliseconds(100);
  const plant_state_t answered = tick();
  EXPECT_EQ(answered.missed_ticks, 1);  // this step had its command
  EXPECT_EQ(answered.command_seq, 1);
  now_ += milliseconds(100);
  const plant_state_t held = tick();  // zero-order hold on command 1: missed
  EXPECT_EQ(held.missed_ticks, 2);
  EXPECT_EQ(held.valve, kAllOpen);

  // A HELLO from some other client answers a state but does not use up a command.
  Exchange([&] { SendCommand(2, kAllOpen); });
  Exchange([&] { SendControl(99, plant_control_t::HELLO); });
  now_ += milliseconds(100);
  EXPECT_EQ(tick().missed_ticks, 2);

  now_ += milliseconds(1500);  // silence beyond --watchdog: one trip, however long
  EXPECT_EQ(tick().watchdog_trips, 1);
  now_ += milliseconds(100);
  EXPECT_EQ(tick().watchdog_trips, 1);
  Exchange([&] { SendCommand(3, kAllOpen); });
  now_ += milliseconds(100);
  EXPECT_FALSE(tick().watchdog_tripped);
  now_ += milliseconds(1500);
  EXPECT_EQ(tick().watchdog_trips, 2);
}

TEST_F(PlantNodeTest, RealtimeStartsTheNextEpisodeOnATickOfItsOwn) {
  StartNode(RunMode::kRealtime);
  // START one step before the interval boundary: the next step truncates.
  const std::int64_t before_boundary = FaultScenario{}.steps_per_interval - 1;
  const plant_state_t started =
      ExchangeOne([&] { SendControl(1, plant_control_t::START, before_boundary); });
  EXPECT_EQ(started.step, 0);
  EXPECT_EQ(started.operating_steps, before_boundary);
  EXPECT_EQ(started.command_seq, 1);

  Exchange([&] { SendCommand(2, kAllOpen); });
  const plant_state_t last = ExchangeOne([&] { node_->Tick(now_); });
  EXPECT_TRUE(last.truncated);
  EXPECT_EQ(last.missed_ticks, 0);
  // The next tick opens the next episode without stepping: its first step
  // waits for a command that answers its initial state.
  const plant_state_t next = ExchangeOne([&] { node_->Tick(now_); });
  EXPECT_EQ(next.step, 0);
  EXPECT_EQ(next.episode, last.episode + 1);
  EXPECT_EQ(next.operating_steps, last.operating_steps);
  EXPECT_EQ(next.missed_ticks, 0);
  EXPECT_EQ(next.true_level, started.true_level);  // full tanks again (no noise, fixed start)
  Exchange([&] { SendCommand(3, kAllClosed); });
  const plant_state_t first = ExchangeOne([&] { node_->Tick(now_); });
  EXPECT_EQ(first.step, 1);
  EXPECT_EQ(first.valve, kAllClosed);
  EXPECT_EQ(first.missed_ticks, 0);
}

TEST_F(PlantNodeTest, RealtimeRepeatedControlIsAnsweredAgainButActsOnce) {
  StartNode(RunMode::kRealtime);
  const plant_state_t reset = ExchangeOne([&] { SendControl(1, plant_control_t::RESET); });
  const plant_state_t again = ExchangeOne([&] { SendControl(1, plant_control_t::RESET); });
  EXPECT_EQ(again.command_seq, 1);
  EXPECT_EQ(again.episode, reset.episode);  // answered, not reset a second time
  EXPECT_EQ(again.duplicate_commands, 1);
}

TEST_F(PlantNodeTest, StartOutsideTheCommandLinesStepBoundIsRejected) {
  // a copy: lcm-gen declares the constant without defining it
  const std::int64_t max_step = plant_control_t::MAX_OPERATING_STEP;
  EXPECT_EQ(max_step, 9'000'000'000'000'000);  // the plant's --start-step bound
  StartNode(RunMode::kRealtime);
  EXPECT_TRUE(Exchange([&] { SendControl(1, plant_control_t::START, -1); }).empty());
  EXPECT_EQ(node_->counters().rejected_commands, 1);
  // INT64_MAX overflowed the step counter (the age went to -1.8e16)
  EXPECT_TRUE(Exchange([&] {
                SendControl(2, plant_control_t::START, std::numeric_limits<std::int64_t>::max());
              }).empty());
  EXPECT_TRUE(Exchange([&] {
                SendControl(3, plant_control_t::START, max_step + 1);
              }).empty());
  EXPECT_EQ(node_->counters().rejected_commands, 3);
  EXPECT_EQ(plant_.operating_steps(), 0);
  const plant_state_t at_bound = ExchangeOne(
      [&] { SendControl(4, plant_control_t::START, max_step); });
  EXPECT_EQ(at_bound.operating_steps, max_step);
  Exchange([&] { SendCommand(5, kAllOpen); });
  const plant_state_t stepped = ExchangeOne([&] { node_->Tick(now_); });
  EXPECT_EQ(stepped.operating_steps, max_step + 1);
  EXPECT_GT(stepped.age, 0.0);
}

// --- Sessions ------------------------------------------------------------------

TEST_F(PlantNodeTest, CommandsOfAnotherSessionAreRefusedAndCounted) {
  StartNode(RunMode::kLockstep);
  ExchangeOne([&] { SendCommand(1, kAllOpen); });
  // a neighbour's command with a seq far ahead (the wall clock in us) and a
  // RESET, SHUTDOWN and CLOSE: none is applied or answered, each is counted
  EXPECT_TRUE(Exchange([&] { SendCommand(1'700'000'000'000'000, kAllClosed, kOther); }).empty());
  EXPECT_TRUE(Exchange([&] { SendCommand(2, kAllClosed, 0); }).empty());
  EXPECT_TRUE(Exchange([&] { SendControl(9, plant_control_t::RESET, 0, kOther); }).empty());
  EXPECT_TRUE(Exchange([&] { SendControl(9, plant_control_t::SHUTDOWN, 0, kOther); }).empty());
  EXPECT_TRUE(Exchange([&] { SendControl(9, plant_control_t::CLOSE, 0, kOther); }).empty());
  EXPECT_FALSE(node_->shutdown_requested());
  EXPECT_EQ(node_->counters().other_session, 5);
  // the session's own next command is neither stale nor preceded
  const plant_state_t next = ExchangeOne([&] { SendCommand(2, kAllOpen); });
  EXPECT_EQ(next.step, 2);
  EXPECT_EQ(next.valve, kAllOpen);
  EXPECT_EQ(next.other_session, 5);
  EXPECT_EQ(next.stale_commands, 0);
  // a HELLO of anyone is answered, in the session the plant follows
  const plant_state_t hello =
      ExchangeOne([&] { SendControl(3, plant_control_t::HELLO, 0, kOther); });
  EXPECT_EQ(hello.session, kSession);
  EXPECT_EQ(hello.command_seq, 3);
}

TEST_F(PlantNodeTest, ANewSessionOpensOnlyWhenTheFollowedOneIsIdleOrClosed) {
  StartNode(RunMode::kLockstep, SafeState::kClosed, /*open=*/false);
  // no session yet: commands are refused, an OPEN of 0 too
  EXPECT_TRUE(Exchange([&] { SendCommand(1, kAllOpen); }).empty());
  EXPECT_TRUE(Exchange([&] { SendControl(1, plant_control_t::OPEN, 0, 0); }).empty());
  EXPECT_EQ(node_->counters().other_session, 2);
  const plant_state_t opened = ExchangeOne([&] { SendControl(1, plant_control_t::START, 5); });
  EXPECT_EQ(opened.session, kSession);
  EXPECT_EQ(opened.operating_steps, 5);
  // another START while the session is active: refused
  now_ += std::chrono::milliseconds(1900);
  EXPECT_TRUE(Exchange([&] { SendControl(1, plant_control_t::START, 0, kOther); }).empty());
  EXPECT_EQ(plant_.operating_steps(), 5);
  // the session's own traffic keeps it active
  ExchangeOne([&] { SendCommand(2, kAllOpen); });
  now_ += std::chrono::milliseconds(1900);
  EXPECT_TRUE(Exchange([&] { SendControl(1, plant_control_t::OPEN, 0, kOther); }).empty());
  EXPECT_EQ(node_->counters().other_session, 4);
  // silent for longer than --session-timeout: its controller is gone
  now_ += std::chrono::milliseconds(2100);
  const plant_state_t taken = ExchangeOne([&] { SendControl(1, plant_control_t::OPEN, 0, kOther); });
  EXPECT_EQ(taken.session, kOther);
  EXPECT_EQ(taken.command_seq, 1);  // its seq counts from its own start
  EXPECT_EQ(taken.step, 1);         // OPEN changes nothing
  EXPECT_TRUE(Exchange([&] { SendCommand(3, kAllOpen); }).empty());  // the old session's
  EXPECT_EQ(ExchangeOne([&] { SendCommand(2, kAllClosed, kOther); }).step, 2);
  // CLOSE releases at once; the old session opens again
  EXPECT_EQ(ExchangeOne([&] { SendControl(3, plant_control_t::CLOSE, 0, kOther); }).session,
            kOther);
  EXPECT_EQ(ExchangeOne([&] { SendControl(7, plant_control_t::OPEN); }).session, kSession);
}

TEST_F(PlantNodeTest, ShutdownWithoutASessionIsObeyedOnlyWhileNobodyIsInControl) {
  StartNode(RunMode::kLockstep, SafeState::kClosed, /*open=*/false);
  EXPECT_EQ(ExchangeOne([&] { SendControl(1, plant_control_t::SHUTDOWN, 0, 0); }).session, 0);
  EXPECT_TRUE(node_->shutdown_requested());
}

TEST_F(PlantNodeTest, HostileLengthsAreCountedAsUndecodable) {
  StartNode(RunMode::kLockstep);
  valve_command_t cmd{};
  cmd.session = kSession;
  cmd.seq = 1;
  cmd.num_valves = 6;
  cmd.valve = kAllOpen;
  std::vector<std::uint8_t> buf(static_cast<std::size_t>(cmd.getEncodedSize()));
  cmd.encode(buf.data(), 0, static_cast<int>(buf.size()));
  buf[8 + 8 * 4] = 0xff;  // num_valves = -1
  EXPECT_TRUE(Exchange([&] {
                lcm_.publish(channels_.command, buf.data(), static_cast<unsigned>(buf.size()));
              }).empty());
  EXPECT_EQ(node_->counters().decode_errors, 1);
  EXPECT_EQ(ExchangeOne([&] { SendCommand(1, kAllOpen); }).step, 1);
}

TEST_F(PlantNodeTest, ShutdownEndsTheLoopAfterAFinalState) {
  StartNode(RunMode::kLockstep);
  SendControl(1, plant_control_t::SHUTDOWN);
  int polls = 0;
  EXPECT_TRUE(node_->Run([&] { return ++polls > 10; }));  // the bound only guards a hang
  EXPECT_TRUE(node_->shutdown_requested());
  EXPECT_EQ(polls, 2);  // asked before and after the one pass that took the SHUTDOWN
  Drain();
  ASSERT_EQ(states_.size(), 1u);
  EXPECT_EQ(states_[0].command_seq, 1);
}

TEST_F(PlantNodeTest, StopPredicateEndsTheLoopAndTheDeadNodeHearsNothing) {
  StartNode(RunMode::kLockstep);
  SendCommand(1, kAllOpen);
  SendCommand(2, kAllOpen);
  EXPECT_TRUE(node_->Run([&] { return plant_.operating_steps() >= 1; }));
  EXPECT_FALSE(node_->shutdown_requested());
  EXPECT_EQ(plant_.operating_steps(), 1);  // command 2 still queued: the loop stopped at once

  node_.reset();  // unsubscribes: command 2, still queued, reaches no handler
  Drain();
  EXPECT_EQ(plant_.operating_steps(), 1);
  ASSERT_EQ(states_.size(), 1u);
  EXPECT_EQ(states_[0].command_seq, 1);
  // memq drops a publish to a channel without subscribers: nothing to handle.
  SendCommand(3, kAllOpen);
  EXPECT_EQ(lcm_.handleTimeout(0), 0);
}

}  // namespace
}  // namespace ftc
