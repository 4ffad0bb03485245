// LCM echo responder: answers every valve command and control message with a
// plant_state_t carrying its seq, exactly as the plant does, but with no
// physics. The lockstep benchmark measures the plant against this floor.
// It follows no session (it answers each message in the message's own) but
// decodes as the plant does: a malformed buffer is counted, never fatal.
#include <lcm/lcm-cpp.hpp>

#include <CLI/CLI.hpp>
#include <csignal>
#include <iostream>

#include "plant/lcm/lcm_bridge.h"
#include "plant/lcm/wire.h"

namespace {

volatile std::sig_atomic_t g_stop = 0;
void OnSignal(int) { g_stop = 1; }

class Echo final {
 public:
  Echo(lcm::LCM* lcm, const std::string& prefix) : lcm_(lcm), channels_(prefix) {
    lcm_->subscribe(channels_.command, &Echo::OnCommand, this);
    lcm_->subscribe(channels_.control, &Echo::OnControl, this);
  }
  bool shutdown() const { return shutdown_; }

 private:
  void OnCommand(const lcm::ReceiveBuffer* rbuf, const std::string& channel) {
    ftc::valve_command_t cmd{};
    if (Decoded(rbuf, channel, &cmd)) Answer(cmd.session, cmd.seq);
  }
  void OnControl(const lcm::ReceiveBuffer* rbuf, const std::string& channel) {
    ftc::plant_control_t msg{};
    if (!Decoded(rbuf, channel, &msg)) return;
    if (msg.command == ftc::plant_control_t::SHUTDOWN) shutdown_ = true;
    Answer(msg.session, msg.seq);
  }
  template <typename T>
  bool Decoded(const lcm::ReceiveBuffer* rbuf, const std::string& channel, T* out) {
    std::string why;
    if (ftc::wire::Decode(rbuf->data, rbuf->data_size, out, &why)) return true;
    ++counters_.decode_errors;
    refusals_.Refused("undecodable message on " + channel + " (" +
                      std::to_string(rbuf->data_size) + " bytes): " + why);
    return false;
  }
  void Answer(std::int64_t session, std::int64_t seq) {
    auto msg = ftc::ToStateMessage(outcome_, ++state_seq_, seq, 0, counters_);
    msg.session = session;
    lcm_->publish(channels_.state, &msg);
  }

  lcm::LCM* lcm_;
  ftc::Channels channels_;
  ftc::StepOutcome outcome_;
  ftc::LinkCounters counters_;
  ftc::wire::RateLimitedLog refusals_{"lcm_echo"};
  std::int64_t state_seq_ = 0;
  bool shutdown_ = false;
};

}  // namespace

int main(int argc, char** argv) {
  std::string url = "udpm://239.255.76.67:7667?ttl=0";
  std::string prefix = "FTC_";
  CLI::App app{"LCM echo responder: the plant's message pattern without physics (benchmark floor)"};
  app.add_option("--lcm-url", url, "LCM provider URL")->capture_default_str();
  app.add_option("--prefix", prefix, "Channel prefix")->capture_default_str();
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e) == 0 ? 0 : 2;
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
  Echo echo(&lcm, prefix);
  std::signal(SIGINT, OnSignal);
  std::signal(SIGTERM, OnSignal);
  while (!g_stop && !echo.shutdown()) {
    if (lcm.handleTimeout(100) < 0 && !g_stop) return 1;
  }
  return 0;
}
