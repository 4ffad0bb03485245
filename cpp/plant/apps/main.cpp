// The plant process: integrates the fuel-transfer plant and serves it over LCM.
// Wiring only: options, signals and the LCM URL policy live here; the protocol
// (lockstep, real-time, watchdog) is ftc::PlantNode (plant/lcm/plant_node.h).
#include <lcm/lcm-cpp.hpp>

#include <CLI/CLI.hpp>
#include <cctype>
#include <cmath>
#include <csignal>
#include <cstdint>
#include <cstdlib>
#include <iostream>
#include <map>
#include <sstream>
#include <string>

#include "plant/core/scenario.h"
#include "plant/lcm/plant_node.h"

namespace {

volatile std::sig_atomic_t g_stop = 0;
void OnSignal(int) { g_stop = 1; }

constexpr int kExitUsage = 2;
constexpr int kExitRuntime = 1;

using ftc::RunMode;
using ftc::SafeState;

struct Options {
  std::string scenario;
  std::string lcm_url = "udpm://239.255.76.67:7667?ttl=0";
  std::uint64_t seed = 0;
  ftc::NodeOptions node;  // prefix, mode, rate, watchdog, safe state, verbose
  int steps_per_interval = 0;  // 0: from the scenario
  std::int64_t start_step = 0;
  bool allow_network = false;
  std::string key_file;  // the bus key (signing.h); else FTC_BUS_KEY, else unsigned
};

// The environment variable a launching controller passes a fresh per-run key
// in (hex), so it never shows on the command line; removed once read.
constexpr const char* kKeyVariable = "FTC_BUS_KEY";

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

// Declared option constraints. Each keeps the description CLI11 shows in --help
// (POSITIVE, NONNEGATIVE, or none) and refuses what CLI11's own checks let
// through: nan (every comparison with it is false), inf, values whose
// conversion overflows, "" and negative numbers given to an unsigned option, and
// an enum's number instead of its name.
constexpr double kMaxRateHz = 1e5;      // a step every 10 us: far above what CVODE keeps up with
constexpr double kMaxWatchdogS = 1e6;   // 11.6 days; std::chrono durations overflow near 1e10 s

CLI::Validator Number(const std::string& description, double low, bool low_open, double high) {
  return CLI::Validator(
      [=](std::string& text) -> std::string {
        double v = 0.0;
        std::istringstream in(text);
        if (text.empty() || !(in >> v) || !in.eof()) return "must be a number, got '" + text + "'";
        if (!std::isfinite(v)) return "must be a finite number, got " + text;
        std::ostringstream bound;
        bound << (low_open ? "> " : ">= ") << low << " and <= " << high;
        if (v < low || (low_open && v == low) || v > high)
          return "must be " + bound.str() + ", got " + text;
        return {};
      },
      description);
}

CLI::Validator Digits() {  // an unsigned integer written as digits only
  return CLI::Validator(
      [](std::string& text) -> std::string {
        if (text.empty()) return "must be an integer >= 0, got ''";
        for (const char c : text)
          if (!std::isdigit(static_cast<unsigned char>(c)))
            return "must be an integer >= 0, got '" + text + "'";
        return {};
      },
      "");
}

CLI::Validator NonEmpty() {
  return CLI::Validator(
      [](std::string& text) -> std::string {
        return text.empty() ? std::string("must not be empty") : std::string();
      },
      "");
}

template <typename T>
CLI::Validator NameOf(const std::map<std::string, T>& names) {  // run before the transformer
  return CLI::Validator(
      [names](std::string& text) -> std::string {
        std::string lower;
        for (const char c : text) lower += static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
        if (names.count(lower)) return {};
        std::string known;
        for (const auto& [name, value] : names) known += (known.empty() ? "" : ", ") + name;
        return "must be one of " + known + ", got '" + text + "'";
      },
      "");
}

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
  // liblcm opens the receive socket on first use; when the port is taken by a
  // socket that does not share it, the subscriptions it leaves crash: ask now
  if (lcm.getFileno() < 0) {
    std::cerr << "plant: error: cannot receive on '" << options.lcm_url
              << "' (its port is taken by another socket)\n";
    return kExitRuntime;
  }

  ftc::NodeOptions node_options = options.node;
  const char* key_hex = std::getenv(kKeyVariable);
  if (key_hex != nullptr && !options.key_file.empty()) {
    std::cerr << "plant: error: both --key-file and " << kKeyVariable << " give a key\n";
    return kExitUsage;
  }
  if (key_hex != nullptr) {
    const std::string why = ftc::signing::KeyFromHex(key_hex, &node_options.key);
    unsetenv(kKeyVariable);
    if (!why.empty()) {
      std::cerr << "plant: error: " << kKeyVariable << ": " << why << "\n";
      return kExitUsage;
    }
  } else if (!options.key_file.empty()) {
    const std::string why = ftc::signing::LoadKey(options.key_file, &node_options.key);
    if (!why.empty()) {
      std::cerr << "plant: error: --key-file " << why << "\n";
      return kExitUsage;
    }
  }

  ftc::Plant plant(scenario, options.seed);
  if (options.start_step > 0) plant.SetOperatingSteps(options.start_step);
  ftc::PlantNode node(&lcm, &plant, node_options);
  std::signal(SIGINT, OnSignal);
  std::signal(SIGTERM, OnSignal);
  if (options.node.verbose)
    std::cerr << "plant: scenario '" << scenario.name << "', "
              << (options.node.mode == RunMode::kLockstep ? "lockstep" : "real-time") << " on "
              << options.lcm_url << " prefix '" << options.node.prefix << "'\n";
  node.PublishState();

  if (!node.Run([] { return g_stop != 0; })) {
    std::cerr << "plant: error: LCM receive failed\n";
    return kExitRuntime;
  }
  if (options.node.verbose) std::cerr << "plant: clean shutdown\n";
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
  app.add_option("--prefix", options.node.prefix,
                 "Channel prefix: <prefix>STATE, <prefix>COMMAND, <prefix>CONTROL")
      ->check(NonEmpty())
      ->capture_default_str();
  app.add_option("--seed", options.seed, "Seed for sensor noise and random starts")
      ->check(Digits())
      ->capture_default_str();
  std::map<std::string, RunMode> modes{{"lockstep", RunMode::kLockstep},
                                       {"realtime", RunMode::kRealtime}};
  app.add_option("--mode", options.node.mode,
                 "lockstep: one step per valve command; realtime: free-running at --rate")
      ->transform(CLI::CheckedTransformer(modes, CLI::ignore_case).description("{lockstep,realtime}"))
      ->transform(NameOf(modes))
      ->default_str("lockstep");
  app.add_option("--rate", options.node.rate_hz, "Real-time mode: control steps per second")
      ->check(Number("POSITIVE", 0.0, true, kMaxRateHz))
      ->capture_default_str();
  app.add_option("--watchdog", options.node.watchdog_s,
                 "Real-time mode: seconds without a valid command before the safe state")
      ->check(Number("POSITIVE", 0.0, true, kMaxWatchdogS))
      ->capture_default_str();
  std::map<std::string, SafeState> safe{{"hold", SafeState::kHold},
                                        {"closed", SafeState::kClosed}};
  app.add_option("--safe-state", options.node.safe_state,
                 "Real-time mode: valves while the watchdog is tripped (hold last or all closed)")
      ->transform(CLI::CheckedTransformer(safe, CLI::ignore_case).description("{hold,closed}"))
      ->transform(NameOf(safe))
      ->default_str("closed");
  app.add_option("--session-timeout", options.node.session_timeout_s,
                 "Seconds without a message of the followed control session after which "
                 "another may open it (START/OPEN)")
      ->check(Number("POSITIVE", 0.0, true, kMaxWatchdogS))
      ->capture_default_str();
  app.add_option("--key-file", options.key_file,
                 "Sign and check every message with the key in this file (hex, mode 600); "
                 "a launching controller passes one in FTC_BUS_KEY instead")
      ->check(NonEmpty());
  app.add_option("--steps-per-interval", options.steps_per_interval,
                 "Override the scenario's control steps per degradation interval")
      ->check(Number("POSITIVE", 0.0, true, 2147483647.0));
  app.add_option("--start-step", options.start_step,
                 "Operating steps already done (resume a run at its age)")
      ->check(Number("NONNEGATIVE", 0.0, false, 9.0e15));  // exact in a double
  // Usage errors are one line naming the flag ("plant: error: --rate: ..."), exit 2.
  app.failure_message([](const CLI::App*, const CLI::Error& e) {
    return std::string("plant: error: ") + e.what() + "\n";
  });
  app.add_flag("--allow-network", options.allow_network,
               "Allow an LCM URL that may leave this machine (warns)");
  app.add_flag("-v,--verbose", options.node.verbose, "Log start, shutdown and watchdog events");
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
