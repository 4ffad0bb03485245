// LCM echo responder: answers every valve command and control message with a
// plant_state_t carrying its seq, exactly as the plant does, but with no
// physics. The lockstep benchmark measures the plant against this floor.
// Its counters move as the plant's do (a command steps the episode and the
// operating age and its valves are applied; RESET, EVALUATE and START begin an
// episode; HELLO, OPEN and CLOSE change nothing; a repeated seq is answered
// again without a step), so a lockstep link's foreign-traffic checks hold.
// Its episodes never end. It follows no session (it answers each message in
// the message's own) but
// decodes as the plant does: a malformed buffer is counted, never fatal. With
// --key-file it checks and signs as the plant does (plant/lcm/signing.h): a
// message without a valid MAC and a rising timestamp is refused and counted,
// and every answer is signed.
#include <lcm/lcm-cpp.hpp>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <chrono>
#include <csignal>
#include <iostream>
#include <optional>

#include "plant/lcm/lcm_bridge.h"
#include "plant/lcm/signing.h"
#include "plant/lcm/wire.h"

namespace {

volatile std::sig_atomic_t g_stop = 0;
void OnSignal(int) { g_stop = 1; }

class Echo final {
 public:
  Echo(lcm::LCM* lcm, const std::string& prefix, const ftc::signing::Key& key)
      : lcm_(lcm), channels_(prefix) {
    lcm_->subscribe(channels_.command, &Echo::OnCommand, this);
    lcm_->subscribe(channels_.control, &Echo::OnControl, this);
    if (!key.empty()) {
      verifier_.emplace(key);
      signer_.emplace(key, /*link_id=*/0);
    }
  }
  bool shutdown() const { return shutdown_; }
  const ftc::LinkCounters& counters() const { return counters_; }

 private:
  void OnCommand(const lcm::ReceiveBuffer* rbuf, const std::string& channel) {
    ftc::valve_command_t cmd{};
    if (!Decoded(rbuf, channel, &cmd)) return;
    Follow(cmd.session);
    if (cmd.seq > answered_seq_) {
      for (int i = 0; i < outcome_.valves.size() && i < cmd.num_valves; ++i)
        outcome_.valves[i] = cmd.valve[i] != 0;
      ++outcome_.step;
      if (!outcome_.evaluation) ++operating_steps_;
      answered_seq_ = cmd.seq;
    }
    Answer(cmd.session, cmd.seq);
  }
  void OnControl(const lcm::ReceiveBuffer* rbuf, const std::string& channel) {
    ftc::plant_control_t msg{};
    if (!Decoded(rbuf, channel, &msg)) return;
    if (msg.command == ftc::plant_control_t::SHUTDOWN) shutdown_ = true;
    Follow(msg.session);
    const bool starts = msg.command == ftc::plant_control_t::RESET ||
                        msg.command == ftc::plant_control_t::EVALUATE ||
                        msg.command == ftc::plant_control_t::START;
    if (starts && msg.seq > answered_seq_) {
      if (msg.command == ftc::plant_control_t::START &&
          msg.operating_step >= 0 && msg.operating_step <= ftc::plant_control_t::MAX_OPERATING_STEP)
        operating_steps_ = msg.operating_step;
      ++outcome_.episode;
      outcome_.step = 0;
      outcome_.evaluation = msg.command == ftc::plant_control_t::EVALUATE;
    }
    if (msg.command != ftc::plant_control_t::HELLO)
      answered_seq_ = std::max(answered_seq_, msg.seq);
    Answer(msg.session, msg.seq);
  }
  // Sequence numbers count within a session: a new one starts them again.
  void Follow(std::int64_t session) {
    if (session == session_) return;
    session_ = session;
    answered_seq_ = 0;
  }
  static std::int64_t NowMicros() {
    return std::chrono::duration_cast<std::chrono::microseconds>(
               std::chrono::system_clock::now().time_since_epoch())
        .count();
  }
  template <typename T>
  bool Decoded(const lcm::ReceiveBuffer* rbuf, const std::string& channel, T* out) {
    std::string why;
    std::size_t size = rbuf->data_size;
    if (verifier_) {
      const auto v = verifier_->Verify(channel, rbuf->data, rbuf->data_size, NowMicros(), &size);
      if (v != ftc::signing::Verdict::kOk) {
        ++(v == ftc::signing::Verdict::kBadSignature ? counters_.bad_signature
           : v == ftc::signing::Verdict::kReplay     ? counters_.replayed
                                                      : counters_.stale_signed);
        refusals_.Refused("refused a message on " + channel + " (" +
                          std::to_string(rbuf->data_size) + " bytes): " +
                          ftc::signing::Describe(v));
        return false;
      }
    }
    if (ftc::wire::Decode(rbuf->data, size, out, &why)) return true;
    ++counters_.decode_errors;
    refusals_.Refused("undecodable message on " + channel + " (" +
                      std::to_string(rbuf->data_size) + " bytes): " + why);
    return false;
  }
  void Answer(std::int64_t session, std::int64_t seq) {
    auto msg = ftc::ToStateMessage(outcome_, ++state_seq_, seq, operating_steps_, counters_);
    msg.session = session;
    if (!signer_) {
      lcm_->publish(channels_.state, &msg);
      return;
    }
    std::vector<unsigned char> buf(static_cast<std::size_t>(msg.getEncodedSize()));
    msg.encode(buf.data(), 0, static_cast<int>(buf.size()));
    const auto out = signer_->Sign(channels_.state, buf.data(), buf.size(), NowMicros());
    lcm_->publish(channels_.state, out.data(), static_cast<unsigned>(out.size()));
  }

  lcm::LCM* lcm_;
  ftc::Channels channels_;
  ftc::StepOutcome outcome_;
  ftc::LinkCounters counters_;
  ftc::wire::RateLimitedLog refusals_{"lcm_echo"};
  std::int64_t state_seq_ = 0;
  std::int64_t session_ = 0;          // session of the last message answered
  std::int64_t answered_seq_ = 0;     // newest command or control seq answered
  std::int64_t operating_steps_ = 0;  // as the plant's: steps outside evaluation
  bool shutdown_ = false;
  std::optional<ftc::signing::Verifier> verifier_;
  std::optional<ftc::signing::Signer> signer_;
};

}  // namespace

int main(int argc, char** argv) {
  std::string url = "udpm://239.255.76.67:7667?ttl=0";
  std::string prefix = "FTC_";
  std::string key_file;
  CLI::App app{"LCM echo responder: the plant's message pattern without physics (benchmark floor)"};
  app.add_option("--lcm-url", url, "LCM provider URL")->capture_default_str();
  app.add_option("--prefix", prefix, "Channel prefix")->capture_default_str();
  app.add_option("--key-file", key_file,
                 "check and sign every message with the bus key in this file (hex, mode 600)");
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e) == 0 ? 0 : 2;
  }
  ftc::signing::Key key;
  if (!key_file.empty()) {
    const std::string why = ftc::signing::LoadKey(key_file, &key);
    if (!why.empty()) {
      std::cerr << "lcm_echo: error: --key-file " << why << "\n";
      return 2;
    }
  }
  lcm::LCM lcm(url);
  if (!lcm.good()) {
    std::cerr << "lcm_echo: error: cannot open LCM at '" << url << "'\n";
    return 1;
  }
  if (lcm.getFileno() < 0) {  // the receive socket (opened on first use) failed
    std::cerr << "lcm_echo: error: cannot receive on '" << url
              << "' (its port is taken by another socket)\n";
    return 1;
  }
  Echo echo(&lcm, prefix, key);
  std::signal(SIGINT, OnSignal);
  std::signal(SIGTERM, OnSignal);
  while (!g_stop && !echo.shutdown()) {
    if (lcm.handleTimeout(100) < 0 && !g_stop) return 1;
  }
  const auto& c = echo.counters();
  if (c.bad_signature + c.replayed + c.stale_signed + c.decode_errors)
    std::cerr << "lcm_echo: refused messages: bad decode " << c.decode_errors
              << ", bad signature " << c.bad_signature << ", replay " << c.replayed
              << ", stale timestamp " << c.stale_signed << "\n";
  return 0;
}
