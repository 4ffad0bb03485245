// The plant process: integrates the fuel-transfer plant and serves it over LCM.
//
//   controller --valve_command_t--> <prefix>COMMAND --+
//   controller --plant_control_t--> <prefix>CONTROL --+--> PlantNode --> Plant (CVODE core)
//   controllers, lcm-logger  <-- <prefix>STATE <-- plant_state_t <--+
//
// Lockstep mode (default): every new valve command advances the plant by one
// 1 s control step and is answered by one state carrying the command's seq.
// A command with the seq already applied is a retry: the last state is sent
// again without stepping. Older seqs are stale and ignored. Both are counted.
// Real-time mode: the plant steps at --rate Hz with zero-order hold on the
// last valid command; a watchdog puts the valves into a safe state when no
// valid command arrives for --watchdog seconds.
#include <lcm/lcm-cpp.hpp>

#include <CLI/CLI.hpp>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <iostream>
#include <optional>
#include <string>

#include "plant/core/scenario.h"
#include "plant/lcm/lcm_bridge.h"

namespace {

volatile std::sig_atomic_t g_stop = 0;
void OnSignal(int) { g_stop = 1; }

constexpr int kExitUsage = 2;
constexpr int kQueueCapacity = 10000;  // messages per subscription
constexpr int kExitRuntime = 1;

enum class RunMode { kLockstep, kRealtime };
enum class SafeState { kHold, kClosed };

struct Options {
  std::string scenario;
  std::string lcm_url = "udpm://239.255.76.67:7667?ttl=0";
  std::string prefix = "FTC_";
  std::uint64_t seed = 0;
  RunMode mode = RunMode::kLockstep;
  double rate_hz = 10.0;
  double watchdog_s = 1.0;
  SafeState safe_state = SafeState::kClosed;
  int steps_per_interval = 0;  // 0: from the scenario
  std::int64_t start_step = 0;
  bool allow_network = false;
  bool verbose = false;
};

// True when a udpm URL leaves the machine: a ttl other than 0 (LCM's default is 0
// only when the option is absent, but we require it to be explicit and zero).
bool UrlIsLoopbackOnly(const std::string& url) {
  // Exactly one ttl option and it is 0: LCM takes the last of repeated options,
  // so "ttl=0&ttl=1" must not pass (found by tests/python/test_fault_injection.py).
  if (url.rfind("udpm://", 0) != 0) return url.rfind("memq://", 0) == 0;
  const auto q = url.find('?');
  if (q == std::string::npos) return false;
  int ttl_options = 0;
  bool ttl_zero = false;
  std::size_t start = q + 1;
  while (start <= url.size()) {
    std::size_t end = url.find('&', start);
    if (end == std::string::npos) end = url.size();
    const std::string opt = url.substr(start, end - start);
    if (opt.rfind("ttl=", 0) == 0) {
      ++ttl_options;
      ttl_zero = opt == "ttl=0";
    }
    start = end + 1;
  }
  return ttl_options == 1 && ttl_zero;
}

class PlantNode final {
 public:
  PlantNode(lcm::LCM* lcm, ftc::Plant* plant, const Options& options)
      : lcm_(lcm),
        plant_(plant),
        options_(options),
        channels_(options.prefix),
        // In real-time mode the valves are in the safe state until a first command.
        watchdog_tripped_(options.mode == RunMode::kRealtime) {
    // LCM keeps at most 30 undispatched messages per subscription by default;
    // a burst beyond that (retries, a flood of garbage) would be dropped
    // silently instead of answered or counted. Bounded, so a flood cannot
    // exhaust memory.
    for (auto* sub : {lcm_->subscribe(channels_.command, &PlantNode::OnCommand, this),
                      lcm_->subscribe(channels_.control, &PlantNode::OnControl, this)})
      sub->setQueueCapacity(kQueueCapacity);
  }

  bool shutdown_requested() const { return shutdown_; }

  void PublishState() { PublishState(answered_seq_); }
  void PublishState(std::int64_t command_seq) {
    auto msg = ftc::ToStateMessage(plant_->last(), ++state_seq_, command_seq,
                                   plant_->operating_steps(), counters_);
    msg.watchdog_tripped = watchdog_tripped_;
    lcm_->publish(channels_.state, &msg);
  }

  // Real-time tick: step with the held valves (or the safe state) and publish.
  void Tick(std::chrono::steady_clock::time_point now) {
    const bool stale = !last_valid_command_time_ ||
                       now - *last_valid_command_time_ >
                           std::chrono::duration<double>(options_.watchdog_s);
    if (stale && !watchdog_tripped_ && options_.verbose)
      std::cerr << "plant: watchdog: no valid command for " << options_.watchdog_s
                << " s, valves to safe state\n";
    watchdog_tripped_ = stale;
    ftc::Valves u = held_;
    if (watchdog_tripped_ && options_.safe_state == SafeState::kClosed) u.setZero();
    plant_->Step(u);
    PublishState();
  }

 private:
  // Sequence rules shared by commands and control messages. Returns true if
  // the message is new and should be acted upon.
  bool Admit(std::int64_t seq) {
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

  void OnCommand(const lcm::ReceiveBuffer* rbuf, const std::string& channel) {
    ftc::valve_command_t cmd;
    if (!ftc::DecodeMessage(rbuf->data, static_cast<int>(rbuf->data_size), &cmd)) {
      ReportDecodeError(channel, rbuf->data_size);
      return;
    }
    if (!Admit(cmd.seq)) return;
    ftc::Valves u;
    std::string reason;
    if (!ftc::ValvesFromCommand(cmd, &u, &reason)) {
      ++counters_.rejected_commands;
      std::cerr << "plant: rejected command seq " << cmd.seq << " on " << channel << ": "
                << reason << "\n";
      return;
    }
    answered_seq_ = cmd.seq;
    if (options_.mode == RunMode::kLockstep) {
      plant_->Step(u);
      PublishState();
    } else {
      held_ = u;
      last_valid_command_time_ = std::chrono::steady_clock::now();
    }
  }

  void OnControl(const lcm::ReceiveBuffer* rbuf, const std::string& channel) {
    ftc::plant_control_t msg;
    if (!ftc::DecodeMessage(rbuf->data, static_cast<int>(rbuf->data_size), &msg)) {
      ReportDecodeError(channel, rbuf->data_size);
      return;
    }
    if (msg.command == ftc::plant_control_t::HELLO) {
      // A handshake is answered whatever its seq (so a new client can attach)
      // and changes nothing, so a repeated HELLO is harmless.
      PublishState(msg.seq);
      return;
    }
    if (!Admit(msg.seq)) return;
    switch (msg.command) {
      case ftc::plant_control_t::RESET:
        plant_->Reset();
        break;
      case ftc::plant_control_t::EVALUATE:
        plant_->ResetEvaluation();
        break;
      case ftc::plant_control_t::SHUTDOWN:
        shutdown_ = true;
        break;
      default:
        ++counters_.rejected_commands;
        std::cerr << "plant: rejected control seq " << msg.seq << ": unknown command "
                  << static_cast<int>(msg.command) << "\n";
        return;
    }
    answered_seq_ = msg.seq;
    PublishState();
  }

  void ReportDecodeError(const std::string& channel, std::uint32_t size) {
    ++counters_.decode_errors;
    std::cerr << "plant: undecodable message on " << channel << " (" << size
              << " bytes): wrong type or corrupt; counted (" << counters_.decode_errors
              << " so far)\n";
  }

  lcm::LCM* lcm_;
  ftc::Plant* plant_;
  Options options_;
  ftc::Channels channels_;
  ftc::LinkCounters counters_;
  std::int64_t state_seq_ = 0;
  std::int64_t answered_seq_ = 0;
  bool shutdown_ = false;
  ftc::Valves held_ = ftc::Valves::Zero();
  std::optional<std::chrono::steady_clock::time_point> last_valid_command_time_;
  bool watchdog_tripped_;
};

int Run(const Options& options) {
  ftc::FaultScenario scenario;
  if (!options.scenario.empty()) scenario = ftc::LoadScenario(options.scenario);
  if (options.steps_per_interval > 0) scenario.steps_per_interval = options.steps_per_interval;

  if (!UrlIsLoopbackOnly(options.lcm_url)) {
    if (!options.allow_network) {
      std::cerr << "plant: error: --lcm-url '" << options.lcm_url
                << "' may leave this machine (udpm needs an explicit ttl=0); pass "
                   "--allow-network to do this on purpose\n";
      return kExitUsage;
    }
    std::cerr << "plant: warning: LCM traffic may leave this machine (" << options.lcm_url
              << ")\n";
  }
  lcm::LCM lcm(options.lcm_url);
  if (!lcm.good()) {
    std::cerr << "plant: error: cannot open LCM at '" << options.lcm_url << "'\n";
    return kExitRuntime;
  }

  ftc::Plant plant(scenario, options.seed);
  if (options.start_step > 0) plant.SetOperatingSteps(options.start_step);
  PlantNode node(&lcm, &plant, options);
  std::signal(SIGINT, OnSignal);
  std::signal(SIGTERM, OnSignal);
  if (options.verbose)
    std::cerr << "plant: scenario '" << scenario.name << "', "
              << (options.mode == RunMode::kLockstep ? "lockstep" : "real-time") << " on "
              << options.lcm_url << " prefix '" << options.prefix << "'\n";
  node.PublishState();

  using Clock = std::chrono::steady_clock;
  const auto period = std::chrono::duration_cast<Clock::duration>(
      std::chrono::duration<double>(1.0 / options.rate_hz));
  auto next_tick = Clock::now() + period;
  while (!g_stop && !node.shutdown_requested()) {
    int timeout_ms = 100;  // bounds the reaction time to a signal
    if (options.mode == RunMode::kRealtime) {
      const auto now = Clock::now();
      if (now >= next_tick) {
        node.Tick(now);
        next_tick += period;
        if (next_tick < now) next_tick = now + period;  // fell behind: do not burst
        continue;
      }
      timeout_ms = static_cast<int>(
          std::chrono::duration_cast<std::chrono::milliseconds>(next_tick - now).count());
    }
    // A signal interrupts the wait (EINTR): that is a shutdown, not a failure.
    if (lcm.handleTimeout(timeout_ms) < 0 && !g_stop) {
      std::cerr << "plant: error: LCM receive failed\n";
      return kExitRuntime;
    }
  }
  if (options.verbose) std::cerr << "plant: clean shutdown\n";
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  Options options;
  CLI::App app{
      "Aircraft fuel-transfer plant (6 tanks, 2 engines, 6 valves) integrated with SUNDIALS "
      "CVODE and served over LCM. It degrades itself with operating age per the fault "
      "scenario; controllers are never told the fault parameters."};
  app.add_option("--scenario", options.scenario,
                 "Fault scenario TOML file (default: the nominal, healthy plant)")
      ->check(CLI::ExistingFile);
  app.add_option("--lcm-url", options.lcm_url, "LCM provider URL (loopback only: keep ttl=0)")
      ->capture_default_str();
  app.add_option("--prefix", options.prefix,
                 "Channel prefix: <prefix>STATE, <prefix>COMMAND, <prefix>CONTROL")
      ->capture_default_str();
  app.add_option("--seed", options.seed, "Seed for sensor noise and random starts")
      ->capture_default_str();
  std::map<std::string, RunMode> modes{{"lockstep", RunMode::kLockstep},
                                       {"realtime", RunMode::kRealtime}};
  app.add_option("--mode", options.mode,
                 "lockstep: one step per valve command; realtime: free-running at --rate")
      ->transform(CLI::CheckedTransformer(modes, CLI::ignore_case).description("{lockstep,realtime}"))
      ->default_str("lockstep");
  app.add_option("--rate", options.rate_hz, "Real-time mode: control steps per second")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  app.add_option("--watchdog", options.watchdog_s,
                 "Real-time mode: seconds without a valid command before the safe state")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  std::map<std::string, SafeState> safe{{"hold", SafeState::kHold},
                                        {"closed", SafeState::kClosed}};
  app.add_option("--safe-state", options.safe_state,
                 "Real-time mode: valves while the watchdog is tripped (hold last or all closed)")
      ->transform(CLI::CheckedTransformer(safe, CLI::ignore_case).description("{hold,closed}"))
      ->default_str("closed");
  app.add_option("--steps-per-interval", options.steps_per_interval,
                 "Override the scenario's control steps per degradation interval")
      ->check(CLI::PositiveNumber);
  app.add_option("--start-step", options.start_step,
                 "Operating steps already done (resume a run at its age)")
      ->check(CLI::NonNegativeNumber);
  app.add_flag("--allow-network", options.allow_network,
               "Allow an LCM URL that may leave this machine (warns)");
  app.add_flag("-v,--verbose", options.verbose, "Log start, shutdown and watchdog events");
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    const int code = app.exit(e);
    return code == 0 ? 0 : kExitUsage;
  }
  try {
    return Run(options);
  } catch (const ftc::ScenarioError& e) {
    std::cerr << "plant: error: " << e.what() << "\n";
    return kExitUsage;
  } catch (const std::exception& e) {
    std::cerr << "plant: error: " << e.what() << "\n";
    return kExitRuntime;
  }
}
