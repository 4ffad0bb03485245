// Fault scenario files (TOML, keys in scenario.h). Strict: anything not
// understood is an error naming the file and the key, never silently ignored,
// because a typo in a fault file would otherwise run a healthy plant.
#include "plant/core/scenario.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <toml++/toml.h>

namespace ftc {
namespace {

constexpr double kMinFactor = 1e-3;  // smallest degradation factor D, intervals

class Reader {
 public:
  explicit Reader(std::string source) : source_(std::move(source)) {}

  [[noreturn]] void Fail(const std::string& key, const std::string& what) const {
    throw ScenarioError(source_ + ": key '" + key + "': " + what);
  }

  static std::string TypeName(const toml::node& n) {
    switch (n.type()) {
      case toml::node_type::string: return "string";
      case toml::node_type::integer: return "integer";
      case toml::node_type::floating_point: return "float";
      case toml::node_type::boolean: return "boolean";
      case toml::node_type::array: return "array";
      case toml::node_type::table: return "table";
      default: return "date/time";
    }
  }

  std::string String(const toml::node& n, const std::string& key) const {
    if (!n.is_string()) Fail(key, "expected a string, got " + TypeName(n));
    return *n.value<std::string>();
  }

  double Number(const toml::node& n, const std::string& key) const {
    if (!n.is_number()) Fail(key, "expected a number, got " + TypeName(n));
    return *n.value<double>();
  }

  // Degradation factors: N numbers, each > 0 (inf = healthy).
  template <int N>
  Eigen::Matrix<double, N, 1> Factors(const toml::node& n, const std::string& key) const {
    const toml::array* a = n.as_array();
    if (a == nullptr) Fail(key, "expected " + std::to_string(N) + " numbers, got " + TypeName(n));
    if (a->size() != N) {
      Fail(key, "expected " + std::to_string(N) + " numbers, got " + std::to_string(a->size()));
    }
    Eigen::Matrix<double, N, 1> v;
    for (int k = 0; k < N; ++k) {
      const toml::node& e = *a->get(k);
      if (!e.is_number()) {
        Fail(key, "element " + std::to_string(k) + " is a " + TypeName(e) + ", expected a number");
      }
      v[k] = *e.value<double>();
      CheckFactor(v[k], key, "element " + std::to_string(k) + " ");
    }
    return v;
  }

  // Tiny factors are accepted by "> 0" but make the wear a/D overflow (a
  // subnormal D gives an infinite resistance) and CVODE fail an interval
  // later, ending the plant mid-run (found by tests/fuzz/fuzz_scenario.cpp).
  // 1e-3 intervals already wears a component out within one control step.
  void CheckFactor(double v, const std::string& key, const std::string& what) const {
    if (std::isnan(v) || !(v >= kMinFactor)) {
      std::ostringstream os;
      os << what << "must be > 0 and at least " << kMinFactor
         << " intervals (inf = healthy), got " << v;
      Fail(key, os.str());
    }
  }

  // An integer in [low, high].
  std::int64_t Integer(const toml::node& n, const std::string& key, std::int64_t low,
                       std::int64_t high, const std::string& what) const {
    if (!n.is_integer()) Fail(key, "expected an integer, got " + TypeName(n));
    const std::int64_t v = *n.value<std::int64_t>();
    if (v < low || v > high) Fail(key, "must be " + what + ", got " + std::to_string(v));
    return v;
  }

  const toml::table& Table(const toml::node& n, const std::string& key) const {
    const toml::table* t = n.as_table();
    if (t == nullptr) Fail(key, "expected a table, got " + TypeName(n));
    return *t;
  }

  const std::string& source() const { return source_; }

 private:
  std::string source_;
};

// One [[event]] table (keys in scenario.h); `key` is "event[n]", n 1-based.
FaultEvent ParseEvent(const Reader& r, const toml::node& node, const std::string& key) {
  const toml::table& t = r.Table(node, key);
  FaultEvent e;
  const toml::node* at_step = nullptr;
  const toml::node* factor = nullptr;
  const toml::node* state = nullptr;
  std::string component;  // the one of tank / engine / stuck_valve given
  for (const auto& [k, sub] : t) {
    const std::string name(k.str());
    const std::string subkey = key + "." + name;
    if (name == "at_step") {
      at_step = &sub;
    } else if (name == "factor") {
      factor = &sub;
    } else if (name == "state") {
      state = &sub;
    } else if (name == "tank" || name == "engine" || name == "stuck_valve") {
      if (!component.empty()) {
        r.Fail(key, "gives both " + component + " and " + name +
                        "; an event changes exactly one of tank, engine, stuck_valve");
      }
      component = name;
      const int count = name == "engine" ? kEngines : kTanks;
      const std::string range = "1.." + std::to_string(count) + " (1-based)";
      e.index = static_cast<int>(r.Integer(sub, subkey, 1, count, range)) - 1;
      e.kind = name == "tank"     ? FaultEvent::Kind::kTank
               : name == "engine" ? FaultEvent::Kind::kEngine
                                  : FaultEvent::Kind::kStuckValve;
    } else {
      r.Fail(subkey, "unknown key (known: at_step, tank, engine, stuck_valve, factor, state)");
    }
  }
  if (at_step == nullptr) r.Fail(key + ".at_step", "missing (the operating step, an integer >= 0)");
  e.at_step = r.Integer(*at_step, key + ".at_step", 0, std::numeric_limits<std::int64_t>::max(),
                        "an integer >= 0 (operating steps)");
  if (component.empty()) r.Fail(key, "needs one of tank, engine, stuck_valve");
  if (e.kind == FaultEvent::Kind::kStuckValve) {
    if (factor != nullptr) r.Fail(key + ".factor", "not allowed for stuck_valve (give state)");
    if (state == nullptr) r.Fail(key + ".state", "missing (\"open\" or \"closed\")");
    const std::string s = r.String(*state, key + ".state");
    if (s != "open" && s != "closed")
      r.Fail(key + ".state", "expected \"open\" or \"closed\", got \"" + s + "\"");
    e.state = s == "open" ? 1 : 0;
  } else {
    if (state != nullptr) r.Fail(key + ".state", "only for stuck_valve (give factor)");
    if (factor == nullptr) r.Fail(key + ".factor", "missing (the new D, intervals; inf = healthy)");
    e.factor = r.Number(*factor, key + ".factor");
    r.CheckFactor(e.factor, key + ".factor", "");
  }
  return e;
}

}  // namespace

FaultScenario ParseScenario(const std::string& toml_text, const std::string& source_name) {
  const Reader r(source_name);
  toml::table root;
  try {
    root = toml::parse(toml_text, source_name);
  } catch (const toml::parse_error& e) {
    std::ostringstream os;
    os << source_name << ":" << e.source().begin.line << ":" << e.source().begin.column
       << ": TOML syntax error: " << e.description();
    throw ScenarioError(os.str());
  }

  FaultScenario s;
  s.name = std::filesystem::path(source_name).stem().string();
  if (s.name.empty()) s.name = "nominal";
  for (const auto& [k, node] : root) {
    const std::string key(k.str());
    if (key == "name") {
      s.name = r.String(node, key);
    } else if (key == "tank_factor") {
      s.tank_factor = r.Factors<kTanks>(node, key);
    } else if (key == "engine_factor") {
      s.engine_factor = r.Factors<kEngines>(node, key);
    } else if (key == "degradation") {
      const std::string mode = r.String(node, key);
      if (mode == "stepwise") {
        s.mode = DegradationMode::kStepwise;
      } else if (mode == "continuous") {
        s.mode = DegradationMode::kContinuous;
      } else {
        r.Fail(key, "expected \"stepwise\" or \"continuous\", got \"" + mode + "\"");
      }
    } else if (key == "steps_per_interval") {
      if (!node.is_integer()) r.Fail(key, "expected an integer, got " + Reader::TypeName(node));
      const std::int64_t n = *node.value<std::int64_t>();
      if (n <= 0 || n > (std::int64_t{1} << 31) - 1) {
        r.Fail(key, "must be a positive 32-bit integer, got " + std::to_string(n));
      }
      s.steps_per_interval = static_cast<int>(n);
    } else if (key == "noise") {
      for (const auto& [sk, sub] : r.Table(node, key)) {
        const std::string subkey = key + "." + std::string(sk.str());
        if (sk.str() != "std") r.Fail(subkey, "unknown key (known: noise.std)");
        const double v = r.Number(sub, subkey);
        if (!std::isfinite(v) || v < 0) {
          std::ostringstream os;
          os << "must be a finite number >= 0 (metres), got " << v;
          r.Fail(subkey, os.str());
        }
        s.noise_std = v;
      }
    } else if (key == "start") {
      for (const auto& [sk, sub] : r.Table(node, key)) {
        const std::string subkey = key + "." + std::string(sk.str());
        if (sk.str() != "random") r.Fail(subkey, "unknown key (known: start.random)");
        if (!sub.is_boolean()) r.Fail(subkey, "expected a boolean, got " + Reader::TypeName(sub));
        s.random_start = *sub.value<bool>();
      }
    } else if (key == "event") {
      const toml::array* events = node.as_array();
      if (events == nullptr || !events->is_array_of_tables()) {
        r.Fail(key, "expected [[event]] tables, got " + Reader::TypeName(node));
      }
      for (std::size_t n = 0; n < events->size(); ++n)
        s.events.push_back(ParseEvent(r, *events->get(n), "event[" + std::to_string(n + 1) + "]"));
      // Any order in the file; applied by step, the file's order within a step.
      std::stable_sort(
          s.events.begin(), s.events.end(),
          [](const FaultEvent& a, const FaultEvent& b) { return a.at_step < b.at_step; });
    } else {
      r.Fail(key,
             "unknown key (known: name, tank_factor, engine_factor, degradation, "
             "steps_per_interval, [noise] std, [start] random, [[event]])");
    }
  }
  return s;
}

FaultScenario LoadScenario(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw ScenarioError(path + ": cannot open the scenario file");
  std::ostringstream text;
  text << in.rdbuf();
  if (in.bad()) throw ScenarioError(path + ": error while reading the scenario file");
  return ParseScenario(text.str(), path);
}

}  // namespace ftc
