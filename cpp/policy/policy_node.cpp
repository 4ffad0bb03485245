// build/policy_node: the embedded controller. It flies a policy exported by
// ftc.export (--weights) on a plant in real-time mode over LCM: every state
// the plant publishes gets one valve command, computed from the newest state
// (and, for a policy with a history window, from the states acted on before
// it in the episode and the commands sent on them), and a pushed policy_t or
// policy_v2_t replaces the policy between two steps (or is rejected with a
// logged reason). At exit it prints one line:
//   steps N deadline_misses M latency_p50_us A latency_p99_us B latency_max_us C
//   auth_us_per_step D
// (latency: from a state's arrival, before its check and decode, to its
// command's send; D: the time spent signing and checking messages per step,
// 0 without a key). A deadline miss is a plant step taken without the command answering the
// state before it (the next state's command_seq is older than that command).
//
// The history is kept as ftc.control.run.realtime's loop keeps the adaptive
// student's (python/ftc/control/agents/learned/adaptive_policy.py): a state
// acted on that opens an episode (step 0, another episode, or the session's
// first) starts it; any other state acted on is pushed with the command sent
// on the state acted on before it. States never acted on (newest-wins) do not
// enter it, as they do not in Python. A policy that reads the stuck memory
// (policy.h History) learns a valve is stuck from a state's published valves
// only when that state answers the command sent on the state acted on before
// (its command_seq) and the watchdog was not holding the valves: a step taken
// on an older command or on the safe state says nothing about a valve (Python's
// agent compares such a step with the command in force; the node keeps only
// its last command and waits for a step that answers it). The
// memory is kept for the node's life, across episodes and sessions (the
// plant's valves stay stuck).
//
// The node opens a control session of its own (OPEN with a random 64-bit id,
// re-sent until the plant answers in it) and acts only on states of that
// session whose seq is newer than the last, but not absurdly so (kMaxSeqJump):
// one fake state cannot poison newest-wins or silence the node. Every buffer
// is checked before decoding (plant/lcm/wire.h); refused messages are counted
// by cause, logged rate-limited, and summed up on stderr at exit. With
// --key-file every message it takes must carry a valid MAC with a rising
// timestamp (plant/lcm/signing.h), and every message it sends is signed.
#include <lcm/lcm-cpp.hpp>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <iostream>
#include <memory>
#include <optional>
#include <random>
#include <vector>

#include "ftc/plant_control_t.hpp"
#include "ftc/policy_ack_t.hpp"
#include "ftc/plant_state_t.hpp"
#include "ftc/policy_t.hpp"
#include "ftc/valve_command_t.hpp"
#include "plant/lcm/signing.h"
#include "plant/lcm/wire.h"
#include "policy/policy.h"
#include "policy/push_wire.h"

namespace {

using Clock = std::chrono::steady_clock;
constexpr std::int64_t kLoggedMisses = 10;  // the first misses are logged, then only counted
// A state more than this ahead of the last one acted on is refused: the plant
// publishes one per tick and LCM queues them, so a real gap is never this big.
constexpr std::int64_t kMaxSeqJump = 1 << 16;
// The OPEN is re-sent this often until answered, and again when no state of
// the session came for kSessionLost (a restarted plant follows no session).
constexpr auto kOpenRetry = std::chrono::milliseconds(250);
constexpr auto kSessionLost = std::chrono::seconds(2);
// The socket's receive buffer unless the URL sets one (recv_buf_size): a
// pushed student (143 kB) reaches the node as ~100 UDP fragments of 1.4 kB,
// which the kernel's default buffer (rmem_default, 208 kB, counting each
// fragment at its allocation's size) did not always hold while the node was
// not scheduled on a loaded machine, and a push with one fragment lost is lost
// whole (measured under a load of 11 to 14: 3 of 6 runs of
// test_node_student.py lost a push, 0 of 4 with a buffer of 4 MB). The
// default student's push is 1.5 MB, ~1,100 fragments; 8 MB holds several
// such pushes at once (the kernel grants it up to net.core.rmem_max).
constexpr int kReceiveBufferBytes = 8 << 20;
volatile std::sig_atomic_t g_stop = 0;
void OnSignal(int) { g_stop = 1; }

std::int64_t WallMicros() {
  return std::chrono::duration_cast<std::chrono::microseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

std::int64_t RandomSession() {
  std::random_device rd;  // the kernel's entropy
  std::int64_t id = 0;
  while (id == 0)
    id = static_cast<std::int64_t>((static_cast<std::uint64_t>(rd()) << 32) ^ rd());
  return id;
}

// "widths 144-384-384-64, window 12, diagonal blocks 1 3 1": what a policy is,
// and the blocks each layer is flown as (Policy::blocks).
std::string Shape(const ftc::policy::Policy& policy) {
  std::string text = "widths ";
  for (std::size_t i = 0; i < policy.widths().size(); ++i)
    text += (i ? "-" : "") + std::to_string(policy.widths()[i]);
  text += ", window " + std::to_string(policy.window());
  if (policy.stuck_memory()) text += ", stuck memory";
  text += ", diagonal blocks";
  for (int k : policy.blocks()) text += " " + std::to_string(k);
  return text;
}

class Node {
 public:
  Node(lcm::LCM* lcm, const std::string& prefix, std::unique_ptr<ftc::policy::Policy> policy,
       const ftc::signing::Key& key)
      : lcm_(lcm),
        command_channel_(prefix + "COMMAND"),
        control_channel_(prefix + "CONTROL"),
        ack_channel_(prefix + "POLICY_ACK"),
        policy_(std::move(policy)) {
    auto* state = lcm_->subscribe(prefix + "STATE", &Node::OnState, this);
    state->setQueueCapacity(1000);  // ~250 kB of states
    // a valid push is at most 2 MB (policy_v2_t::MAX_PARAMS); LCM drops what
    // arrives beyond 8 queued ones before the node sees it (bounded memory)
    lcm_->subscribe(prefix + "POLICY", &Node::OnPolicy, this)->setQueueCapacity(8);
    if (!key.empty()) {
      verifier_.emplace(key);
      signer_.emplace(key, static_cast<std::uint8_t>(1 + session_ % 255));
    }
  }

  // Waits up to timeout_ms for messages, takes every queued one, then acts on
  // the newest state if there is a new one. Returns false on an LCM error.
  //
  // With a warm-up lead (--warm-ms), the wait ends that long before the next
  // state is due (the last state's arrival plus the states' mean period), and
  // the policy runs the pass the state will take once, its result dropped
  // (Policy::Warm): the weights it reads are back in the cache when it
  // comes. Between two states at 100 Hz other processes evict them. A cold
  // forward pass of the three-member student (0.5 MB of weights, packed) took
  // 19 us at p50 and 29 us at p99 against 4 us warm (build/bench_forward).
  bool Spin(int timeout_ms) {
    const auto now = Clock::now();
    if (!open_ || now - heard_ > kSessionLost) Open(now);
    int wait = timeout_ms;
    if (warm_lead_.count() > 0 && period_.count() > 0 && !warmed_) {
      const auto warm_at = received_ + period_ - warm_lead_;
      // LCM waits whole milliseconds: under one to go, warm now rather than spin
      const auto until = std::chrono::duration_cast<std::chrono::milliseconds>(warm_at - now);
      if (until.count() < 1)
        Warm();
      else
        wait = std::min<int>(wait, static_cast<int>(until.count()));
    }
    if (lcm_->handleTimeout(wait) < 0) return false;
    while (lcm_->handleTimeout(0) > 0) {
    }
    if (pending_) Act();
    return true;
  }

  void set_warm_lead(std::chrono::microseconds lead) { warm_lead_ = lead; }
  std::int64_t warmups() const { return warmups_; }
  std::int64_t prepared_steps() const { return prepared_steps_ + policy_->prepared_acts(); }

  std::int64_t steps() const { return steps_; }
  std::int64_t misses() const { return misses_; }
  std::int64_t watchdog_states() const { return watchdog_states_; }
  std::vector<double>& latencies_us() { return latencies_us_; }
  // time spent signing and checking messages (HMAC), per step acted on
  double auth_us_per_step() const {
    return steps_ ? std::chrono::duration<double, std::micro>(auth_time_).count() /
                        static_cast<double>(steps_)
                  : 0.0;
  }
  std::string refused() const {
    return "bad decode " + std::to_string(bad_decode_) + ", other session " +
           std::to_string(other_session_) + ", stale " + std::to_string(stale_) +
           ", seq jump " + std::to_string(jumps_) + ", bad signature " +
           std::to_string(bad_signature_) + ", replay " + std::to_string(replay_) +
           ", stale timestamp " + std::to_string(stale_signed_);
  }
  std::int64_t refused_total() const {
    return bad_decode_ + other_session_ + stale_ + jumps_ + bad_signature_ + replay_ +
           stale_signed_;
  }

 private:
  template <typename T>
  void Publish(const std::string& channel, const T& msg) {
    if (!signer_) {
      lcm_->publish(channel, &msg);
      return;
    }
    std::vector<unsigned char> buf(static_cast<std::size_t>(msg.getEncodedSize()));
    msg.encode(buf.data(), 0, static_cast<int>(buf.size()));
    const auto t0 = Clock::now();
    const auto out = signer_->Sign(channel, buf.data(), buf.size(), WallMicros());
    auth_time_ += Clock::now() - t0;
    lcm_->publish(channel, out.data(), static_cast<unsigned>(out.size()));
  }

  // With a key: checks the trailer, *size the payload's; false (counted) if refused.
  bool Authentic(const lcm::ReceiveBuffer* rbuf, const std::string& channel, std::size_t* size) {
    *size = rbuf->data_size;
    if (!verifier_) return true;
    const auto t0 = Clock::now();
    const auto v = verifier_->Verify(channel, rbuf->data, rbuf->data_size, WallMicros(), size);
    auth_time_ += Clock::now() - t0;
    if (v == ftc::signing::Verdict::kOk) return true;
    ++(v == ftc::signing::Verdict::kBadSignature ? bad_signature_
       : v == ftc::signing::Verdict::kReplay     ? replay_
                                                  : stale_signed_);
    log_.Refused("refused a message on " + channel + ": " + ftc::signing::Describe(v));
    return false;
  }

  void Open(Clock::time_point now) {
    if (open_) {  // the plant stopped answering in our session: open it again
      open_ = false;
      acted_ = false;  // the history starts again with the next state acted on
      std::cerr << "policy_node: no state of session " << session_ << " for "
                << std::chrono::duration_cast<std::chrono::seconds>(kSessionLost).count()
                << " s; opening it again\n";
    }
    if (open_seq_ != 0 && now - opened_at_ < kOpenRetry) return;
    if (open_seq_ == 0 || now - opened_at_ > kSessionLost) open_seq_ = ++seq_;
    ftc::plant_control_t msg{};
    msg.utime = WallMicros();
    msg.session = session_;
    msg.seq = open_seq_;
    msg.command = ftc::plant_control_t::OPEN;
    Publish(control_channel_, msg);
    opened_at_ = now;
  }

  void OnState(const lcm::ReceiveBuffer* rbuf, const std::string& channel) {
    const auto arrived = Clock::now();  // the latency counts the check and the decode too
    ftc::plant_state_t m{};
    std::string why;
    std::size_t size = 0;
    if (!Authentic(rbuf, channel, &size)) return;
    if (!ftc::wire::Decode(rbuf->data, size, &m, &why)) {
      ++bad_decode_;
      log_.Refused("undecodable state on " + channel + ": " + why);
      return;
    }
    const ftc::plant_state_t* s = &m;
    if (s->session != session_) {
      ++other_session_;
      if (open_)  // (before its OPEN is answered the plant follows another session: normal)
        log_.Refused("ignored state " + std::to_string(s->seq) + " of session " +
                   std::to_string(s->session) + " (ours: " + std::to_string(session_) + ")");
      return;
    }
    if (!open_) {
      if (s->command_seq != open_seq_) return;  // an answer to an earlier OPEN of ours
      open_ = true;  // the answer to our OPEN: newest-wins starts from it
      last_state_seq_ = s->seq - 1;
      std::cerr << "policy_node: session " << session_ << " open\n";
    }
    if (s->seq <= last_state_seq_ || s->seq - last_state_seq_ > kMaxSeqJump) {
      ++(s->seq <= last_state_seq_ ? stale_ : jumps_);
      log_.Refused("ignored state " + std::to_string(s->seq) + ": the last was " +
                   std::to_string(last_state_seq_));
      return;
    }
    if (s->num_tanks != ftc::policy::kTanks) {
      ++bad_decode_;
      log_.Refused("ignored state " + std::to_string(s->seq) + ": num_tanks " +
                   std::to_string(s->num_tanks));
      return;
    }
    heard_ = Clock::now();
    if (acted_) {  // the states' mean period (received_: the previous state's arrival)
      const auto gap = std::chrono::duration_cast<std::chrono::microseconds>(arrived - received_);
      if (gap < std::chrono::seconds(1))
        period_ = period_.count() == 0 ? gap : (period_ * 7 + gap) / 8;
    }
    if (last_sent_seq_ && s->command_seq < *last_sent_seq_) {
      if (++misses_ <= kLoggedMisses)
        std::cerr << "policy_node: deadline miss: the plant took step " << s->step
                  << " of episode " << s->episode << " (state " << s->seq
                  << ") before command " << *last_sent_seq_ << " arrived\n";
    }
    if (s->watchdog_tripped) ++watchdog_states_;
    last_state_seq_ = s->seq;
    pending_ = *s;
    received_ = arrived;
  }

  // A push's fields, whichever version of the message carried them.
  struct Push {
    std::int64_t utime = 0, version = 0, checksum = 0;
    int window = 0;
    bool stuck_memory = false;
    bool v2 = false;
    std::vector<int> widths;
    std::vector<float> params;
  };

  // Decodes a policy_v2_t (told by its fingerprint) or a policy_t; "" or the reason.
  static std::string DecodePush(const void* data, std::size_t size, Push* out) {
    std::string why;
    if (ftc::policy::IsPolicyV2(data, size)) {
      ftc::policy_v2_t m{};
      if (!ftc::policy::DecodePolicyV2(data, size, &m, &why)) return why;
      if (m.stuck_memory != 0 && m.stuck_memory != 1)
        return "stuck_memory " + std::to_string(m.stuck_memory) + " (0 or 1 expected)";
      *out = {m.utime, m.version, m.checksum, m.window, m.stuck_memory == 1, true,
              std::vector<int>(m.widths.begin(), m.widths.end()),
              std::vector<float>(m.params.begin(), m.params.end())};
      return {};
    }
    ftc::policy_t m{};
    if (!ftc::wire::Decode(data, size, &m, &why))
      return why + " (nor a " + ftc::policy_v2_t::getTypeName() + ")";
    *out = {m.utime, m.version, m.checksum, 0, false, false,
            std::vector<int>(m.widths.begin(), m.widths.end()),
            std::vector<float>(m.params.begin(), m.params.end())};
    return {};
  }

  void OnPolicy(const lcm::ReceiveBuffer* rbuf, const std::string& channel) {
    Push m;
    std::string why;
    std::size_t size = 0;
    if (!Authentic(rbuf, channel, &size)) {
      Ack(0, 0, "bad signature, replayed or stale");
      return;
    }
    why = DecodePush(rbuf->data, size, &m);
    if (!why.empty()) {
      ++bad_decode_;
      why = "undecodable push (" + std::to_string(rbuf->data_size) + " bytes): " + why;
      log_.Refused("rejected an " + why + " on " + channel);
      Ack(0, 0, why);
      return;
    }
    const auto expected = m.v2 ? ftc::policy::Checksum(m.widths, m.params, m.window,
                                                       m.stuck_memory)
                               : ftc::policy::Checksum(m.widths, m.params);
    if (m.version <= policy_->version()) {
      why = "version " + std::to_string(m.version) + " is not above the running " +
            std::to_string(policy_->version());
    } else if (static_cast<std::uint64_t>(m.checksum) != expected) {
      why = "checksum mismatch (corrupted in transit or made by other code)";
    }
    std::unique_ptr<ftc::policy::Policy> next;
    if (why.empty())
      next = ftc::policy::Policy::Make(m.window, std::move(m.widths), std::move(m.params),
                                       m.version, &why, m.stuck_memory);
    if (!next) {
      std::cerr << "policy_node: rejected policy version " << m.version << ": " << why
                << "; keeping version " << policy_->version() << "\n";
      Ack(m.version, m.utime, why);
      return;
    }
    prepared_steps_ += policy_->prepared_acts();
    policy_ = std::move(next);  // between two states: the next one is acted on by it
    if (acted_) policy_->Prepare(history_);  // its own sums of the history kept
    std::cerr << "policy_node: policy version " << policy_->version() << " in use ("
              << Shape(*policy_) << ")\n";
    Ack(m.version, m.utime, "");
  }

  // Answers a push: accepted when `why` is empty.
  void Ack(std::int64_t version, std::int64_t push_utime, std::string why) {
    ftc::policy_ack_t ack{};
    ack.utime = WallMicros();
    ack.version = version;
    ack.push_utime = push_utime;
    ack.accepted = why.empty();
    ack.running_version = policy_->version();
    if (why.size() > static_cast<std::size_t>(ftc::policy_ack_t::MAX_REASON))
      why.resize(static_cast<std::size_t>(ftc::policy_ack_t::MAX_REASON));
    ack.reason = why;
    Publish(ack_channel_, ack);
  }

  void Act() {
    std::array<double, ftc::policy::kTanks> level{};
    std::copy(pending_->level.begin(), pending_->level.end(), level.begin());
    if (!acted_ || pending_->step == 0 || pending_->episode != episode_)
      history_.Start(level);
    else
      history_.Push(level, last_u_, Applied(*pending_));
    const auto u = policy_->Act(history_);
    acted_ = true;
    episode_ = pending_->episode;
    last_u_ = u;
    ftc::valve_command_t cmd{};
    cmd.utime = WallMicros();
    cmd.session = session_;
    cmd.seq = ++seq_;
    cmd.state_seq = pending_->seq;
    cmd.num_valves = ftc::policy::kTanks;
    cmd.valve.assign(u.begin(), u.end());
    Publish(command_channel_, cmd);
    latencies_us_.push_back(
        std::chrono::duration<double, std::micro>(Clock::now() - received_).count());
    // off the deadline, before the next state: the first layer's products of
    // the steps the next state's window keeps (Policy::Prepare)
    policy_->Prepare(history_);
    last_sent_seq_ = cmd.seq;
    pending_.reset();
    warmed_ = false;
    ++steps_;
  }

  // The valves the plant applied on the step that led to state `s`, for the
  // stuck memory: its published valves if that step was taken on the command
  // sent on the state acted on before (its command_seq) and the watchdog did
  // not hold the valves; otherwise the command itself, which says nothing (the
  // plant applied an older command or its safe state, not a stuck valve).
  std::array<std::int8_t, ftc::policy::kTanks> Applied(const ftc::plant_state_t& s) const {
    if (!last_sent_seq_ || s.command_seq != *last_sent_seq_ || s.watchdog_tripped)
      return last_u_;
    std::array<std::int8_t, ftc::policy::kTanks> applied{};
    for (int i = 0; i < ftc::policy::kTanks; ++i) applied[i] = s.valve[i] != 0;
    return applied;
  }

  // The pass the next state will take, its result dropped (see Spin).
  void Warm() {
    policy_->Warm();
    warmed_ = true;
    ++warmups_;
  }

  lcm::LCM* lcm_;
  std::string command_channel_, control_channel_, ack_channel_;
  std::unique_ptr<ftc::policy::Policy> policy_;
  std::optional<ftc::plant_state_t> pending_;
  ftc::policy::History history_;  // of the states acted on in this episode
  bool acted_ = false;            // on a state of this session
  std::int32_t episode_ = 0;      // of the state acted on last
  std::array<std::int8_t, ftc::policy::kTanks> last_u_{};  // the command sent on it
  Clock::time_point received_;
  const std::int64_t session_ = RandomSession();
  bool open_ = false;
  std::int64_t open_seq_ = 0;  // seq of the OPEN being sent
  Clock::time_point opened_at_, heard_;
  std::int64_t last_state_seq_ = 0;
  std::optional<std::int64_t> last_sent_seq_;
  std::int64_t seq_ = 0;  // counts within the session
  std::int64_t steps_ = 0, misses_ = 0, watchdog_states_ = 0;
  std::int64_t bad_decode_ = 0, other_session_ = 0, stale_ = 0, jumps_ = 0;
  std::int64_t bad_signature_ = 0, replay_ = 0, stale_signed_ = 0;
  std::optional<ftc::signing::Verifier> verifier_;
  std::optional<ftc::signing::Signer> signer_;
  ftc::wire::RateLimitedLog log_{"policy_node"};
  std::vector<double> latencies_us_;
  Clock::duration auth_time_{};
  std::chrono::microseconds warm_lead_{0}, period_{0};
  bool warmed_ = true;  // none before the first state is acted on
  std::int64_t warmups_ = 0;
  std::int64_t prepared_steps_ = 0;  // of the policies flown before the current one
};

double Percentile(std::vector<double> v, double q) {
  if (v.empty()) return 0.0;
  std::sort(v.begin(), v.end());
  const auto i = static_cast<std::size_t>(std::ceil(q * static_cast<double>(v.size())) - 1);
  return v[std::min(i, v.size() - 1)];
}

}  // namespace

int main(int argc, char** argv) {
  std::string policy_path, url, prefix = "FTC_", latency_log, key_file;
  std::int64_t max_steps = 0;
  CLI::App app{"The embedded controller: flies an exported policy (ftc.export --weights) on a "
               "plant in real-time mode over LCM; takes pushed policy_t / policy_v2_t weights "
               "between steps"};
  app.add_option("--policy", policy_path, "weights file written by ftc.export --weights")
      ->required();
  app.add_option("--lcm-url", url, "LCM provider URL (must keep ttl=0: loopback only)")
      ->required();
  app.add_option("--prefix", prefix, "channel prefix of the plant")->capture_default_str();
  app.add_option("--latency-log", latency_log,
                 "write each step's latency (state received to command sent, microseconds), "
                 "one per line, to this file at exit");
  app.add_option("--key-file", key_file,
                 "sign and check every message with the key in this file (hex, mode 600)");
  app.add_option("--steps", max_steps, "stop after acting on this many states (0: until a signal)")
      ->check(CLI::NonNegativeNumber);
  double warm_ms = 1.0;
  app.add_option("--warm-ms", warm_ms,
                 "run the policy once this long before the next state is due (the states' mean "
                 "period after the last), so its weights are in the cache when it comes; 0: never")
      ->check(CLI::Range(0.0, 1000.0))
      ->capture_default_str();
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e) == 0 ? 0 : 2;
  }
  if (url.find("ttl=0") == std::string::npos) {
    std::cerr << "policy_node: --lcm-url " << url << " lacks ttl=0 (loopback only)\n";
    return 2;
  }
  ftc::signing::Key key;
  if (!key_file.empty()) {
    const std::string why = ftc::signing::LoadKey(key_file, &key);
    if (!why.empty()) {
      std::cerr << "policy_node: --key-file " << why << "\n";
      return 2;
    }
  }
  std::string error;
  auto policy = ftc::policy::Policy::FromFile(policy_path, &error);
  if (!policy) {
    std::cerr << "policy_node: " << error << "\n";
    return 2;
  }
  if (url.find("recv_buf_size=") == std::string::npos)
    url += "&recv_buf_size=" + std::to_string(kReceiveBufferBytes);  // (ttl=0 gave it a '?')
  lcm::LCM lcm(url);
  if (!lcm.good()) {
    std::cerr << "policy_node: cannot open LCM at " << url << "\n";
    return 1;
  }
  std::cerr << "policy_node: flying " << policy_path << " (" << Shape(*policy) << ")\n";
  std::signal(SIGINT, OnSignal);
  std::signal(SIGTERM, OnSignal);
  Node node(&lcm, prefix, std::move(policy), key);
  node.set_warm_lead(std::chrono::microseconds(static_cast<std::int64_t>(warm_ms * 1000.0)));
  while (!g_stop && (max_steps == 0 || node.steps() < max_steps)) {
    if (!node.Spin(100) && !g_stop) {
      std::cerr << "policy_node: LCM failed while waiting for the plant\n";
      return 1;
    }
  }
  auto& lat = node.latencies_us();
  if (!latency_log.empty()) {
    std::FILE* f = std::fopen(latency_log.c_str(), "w");
    if (f == nullptr) {
      std::cerr << "policy_node: cannot write " << latency_log << "\n";
      return 5;
    }
    for (double us : lat) std::fprintf(f, "%.1f\n", us);
    std::fclose(f);
  }
  std::printf("steps %lld deadline_misses %lld latency_p50_us %.0f latency_p99_us %.0f "
              "latency_max_us %.0f auth_us_per_step %.2f\n",
              static_cast<long long>(node.steps()), static_cast<long long>(node.misses()),
              Percentile(lat, 0.50), Percentile(lat, 0.99),
              lat.empty() ? 0.0 : *std::max_element(lat.begin(), lat.end()),
              node.auth_us_per_step());
  if (node.refused_total())
    std::cerr << "policy_node: refused messages: " << node.refused() << "\n";
  if (node.warmups())
    std::cerr << "policy_node: " << node.warmups() << " warm-ups before states\n";
  if (node.prepared_steps())
    std::cerr << "policy_node: " << node.prepared_steps() << " of " << node.steps()
              << " steps acted on with the first layer's older steps summed before they came\n";
  if (node.watchdog_states())
    std::cerr << "policy_node: " << node.watchdog_states()
              << " states with the plant's watchdog tripped\n";
  return 0;
}
