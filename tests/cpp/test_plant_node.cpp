// PlantNode's protocol (lockstep answers, retries, stale and duplicate
// messages, the real-time watchdog, shutdown) on memq://, with a fake clock.
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

  void StartNode(RunMode mode, SafeState safe_state = SafeState::kClosed) {
    NodeOptions options;
    options.prefix = kPrefix;
    options.mode = mode;
    options.rate_hz = 10.0;
    options.watchdog_s = 1.0;
    options.safe_state = safe_state;
    node_ = std::make_unique<PlantNode>(&lcm_, &plant_, options, [this] { return now_; });
  }

  void SendCommand(std::int64_t seq, const std::vector<std::int8_t>& valves) {
    valve_command_t cmd;
    cmd.utime = 0;
    cmd.seq = seq;
    cmd.state_seq = 0;
    cmd.num_valves = static_cast<std::int8_t>(valves.size());
    cmd.valve = valves;
    lcm_.publish(channels_.command, &cmd);
  }

  void SendControl(std::int64_t seq, std::int8_t command) {
    plant_control_t msg;
    msg.utime = 0;
    msg.seq = seq;
    msg.command = command;
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

  static constexpr const char* kPrefix = "TEST_";
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
  const auto initial = Exchange([&] { node_->PublishState(); });
  ASSERT_EQ(initial.size(), 1u);
  EXPECT_EQ(initial[0].seq, 1);
  EXPECT_EQ(initial[0].command_seq, 0);
  EXPECT_EQ(initial[0].step, 0);

  const auto first = Exchange([&] { SendCommand(1, kAllOpen); });
  ASSERT_EQ(first.size(), 1u);
  EXPECT_EQ(first[0].seq, 2);
  EXPECT_EQ(first[0].command_seq, 1);
  EXPECT_EQ(first[0].step, 1);
  EXPECT_EQ(first[0].operating_steps, 1);
  EXPECT_EQ(first[0].valve, kAllOpen);
  EXPECT_NE(first[0].true_level, initial[0].true_level);  // it did step

  const auto second = Exchange([&] { SendCommand(2, kAllClosed); });
  ASSERT_EQ(second.size(), 1u);
  EXPECT_EQ(second[0].command_seq, 2);
  EXPECT_EQ(second[0].step, 2);
  EXPECT_EQ(second[0].valve, kAllClosed);
  EXPECT_EQ(plant_.operating_steps(), 2);
  EXPECT_EQ(second[0].duplicate_commands + second[0].stale_commands +
                second[0].rejected_commands + second[0].decode_errors,
            0);
}

TEST_F(PlantNodeTest, RetryResendsTheLastStateWithoutStepping) {
  StartNode(RunMode::kLockstep);
  const auto answer = Exchange([&] { SendCommand(1, kAllOpen); });
  ASSERT_EQ(answer.size(), 1u);
  EXPECT_EQ(answer[0].duplicate_commands, 0);

  const auto retry = Exchange([&] { SendCommand(1, kAllOpen); });
  ASSERT_EQ(retry.size(), 1u);  // the lost answer, sent again
  EXPECT_EQ(retry[0].seq, answer[0].seq + 1);
  EXPECT_EQ(retry[0].command_seq, 1);
  EXPECT_EQ(retry[0].step, 1);
  EXPECT_EQ(retry[0].true_level, answer[0].true_level);
  EXPECT_EQ(retry[0].duplicate_commands, 1);
  EXPECT_EQ(plant_.operating_steps(), 1);
}

TEST_F(PlantNodeTest, StaleSeqIsIgnoredAndCounted) {
  StartNode(RunMode::kLockstep);
  ASSERT_EQ(Exchange([&] { SendCommand(5, kAllOpen); }).size(), 1u);

  EXPECT_TRUE(Exchange([&] { SendCommand(3, kAllClosed); }).empty());
  EXPECT_EQ(plant_.operating_steps(), 1);
  EXPECT_EQ(node_->counters().stale_commands, 1);

  const auto next = Exchange([&] { SendCommand(6, kAllClosed); });
  ASSERT_EQ(next.size(), 1u);
  EXPECT_EQ(next[0].command_seq, 6);
  EXPECT_EQ(next[0].step, 2);
  EXPECT_EQ(next[0].stale_commands, 1);
  EXPECT_EQ(next[0].duplicate_commands, 0);
}

TEST_F(PlantNodeTest, DuplicateResetResetsOnceAndResendsItsAnswer) {
  StartNode(RunMode::kLockstep);
  ASSERT_EQ(Exchange([&] { SendCommand(1, kAllOpen); }).size(), 1u);

  const auto reset = Exchange([&] { SendControl(2, plant_control_t::RESET); });
  ASSERT_EQ(reset.size(), 1u);
  EXPECT_EQ(reset[0].command_seq, 2);
  EXPECT_EQ(reset[0].episode, 1);
  EXPECT_EQ(reset[0].step, 0);

  const auto duplicate = Exchange([&] { SendControl(2, plant_control_t::RESET); });
  ASSERT_EQ(duplicate.size(), 1u);
  EXPECT_EQ(duplicate[0].command_seq, 2);
  EXPECT_EQ(duplicate[0].episode, 1);  // a second Reset would make it 2
  EXPECT_EQ(duplicate[0].duplicate_commands, 1);
}

TEST_F(PlantNodeTest, HelloIsAnsweredWithItsSeqEveryTimeAndChangesNothing) {
  StartNode(RunMode::kLockstep);
  ASSERT_EQ(Exchange([&] { SendCommand(4, kAllOpen); }).size(), 1u);
  for (int k = 0; k < 2; ++k) {
    const auto hello = Exchange([&] { SendControl(100, plant_control_t::HELLO); });
    ASSERT_EQ(hello.size(), 1u);
    EXPECT_EQ(hello[0].command_seq, 100);
    EXPECT_EQ(hello[0].step, 1);
    EXPECT_EQ(hello[0].duplicate_commands, 0);
  }
  // The HELLO's seq was not taken as applied: seq 5 is new, not stale.
  const auto next = Exchange([&] { SendCommand(5, kAllOpen); });
  ASSERT_EQ(next.size(), 1u);
  EXPECT_EQ(next[0].step, 2);
  EXPECT_EQ(next[0].stale_commands, 0);
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
                cmd.seq = 4;
                cmd.state_seq = 0;
                cmd.num_valves = 6;
                cmd.valve = kAllOpen;
                lcm_.publish(channels_.control, &cmd);
              }).empty());
  EXPECT_EQ(plant_.operating_steps(), 0);

  // A rejected seq is not taken as applied: the same seq, valid, steps.
  const auto valid = Exchange([&] { SendCommand(1, kAllOpen); });
  ASSERT_EQ(valid.size(), 1u);
  EXPECT_EQ(valid[0].step, 1);
  EXPECT_EQ(valid[0].rejected_commands, 3);
  EXPECT_EQ(valid[0].decode_errors, 2);
  EXPECT_EQ(valid[0].duplicate_commands, 0);
}

TEST_F(PlantNodeTest, RealtimeStartsInTheSafeState) {
  StartNode(RunMode::kRealtime);
  const auto tick = Exchange([&] { node_->Tick(now_); });
  ASSERT_EQ(tick.size(), 1u);
  EXPECT_TRUE(tick[0].watchdog_tripped);
  EXPECT_EQ(tick[0].valve, kAllClosed);
  EXPECT_EQ(tick[0].command_seq, 0);
  EXPECT_EQ(tick[0].step, 1);
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
    return Exchange([&] { ASSERT_TRUE(node_->RunOnce()); });
  };
  const auto held = tick_at(milliseconds(100));
  ASSERT_EQ(held.size(), 1u);
  EXPECT_FALSE(held[0].watchdog_tripped);
  EXPECT_EQ(held[0].valve, kAllOpen);
  EXPECT_EQ(held[0].command_seq, 1);

  const auto at_limit = tick_at(milliseconds(1000));  // exactly --watchdog: still valid
  ASSERT_EQ(at_limit.size(), 1u);
  EXPECT_FALSE(at_limit[0].watchdog_tripped);
  EXPECT_EQ(at_limit[0].valve, kAllOpen);

  const auto tripped = tick_at(milliseconds(1100));
  ASSERT_EQ(tripped.size(), 1u);
  EXPECT_TRUE(tripped[0].watchdog_tripped);
  EXPECT_EQ(tripped[0].valve, kAllClosed);

  // A new valid command clears it at the next tick.
  now_ = t0 + milliseconds(1150);
  SendCommand(2, kAllOpen);
  ASSERT_TRUE(node_->RunOnce());
  const auto recovered = tick_at(milliseconds(1200));
  ASSERT_EQ(recovered.size(), 1u);
  EXPECT_FALSE(recovered[0].watchdog_tripped);
  EXPECT_EQ(recovered[0].valve, kAllOpen);
  EXPECT_EQ(recovered[0].command_seq, 2);
}

TEST_F(PlantNodeTest, RealtimeHoldSafeStateKeepsTheLastValves) {
  StartNode(RunMode::kRealtime, SafeState::kHold);
  SendCommand(1, kAllOpen);
  ASSERT_TRUE(node_->RunOnce());
  now_ += milliseconds(1500);
  const auto tripped = Exchange([&] { ASSERT_TRUE(node_->RunOnce()); });
  ASSERT_EQ(tripped.size(), 1u);
  EXPECT_TRUE(tripped[0].watchdog_tripped);
  EXPECT_EQ(tripped[0].valve, kAllOpen);
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

  node_.reset();  // unsubscribes: command 2 and later ones reach no handler
  Drain();
  SendCommand(3, kAllOpen);
  Drain();
  EXPECT_EQ(plant_.operating_steps(), 1);
  ASSERT_EQ(states_.size(), 1u);
  EXPECT_EQ(states_[0].command_seq, 1);
}

}  // namespace
}  // namespace ftc
