// Fault scenario files (TOML, keys in scenario.h). Strict: anything not
// understood is an error naming the file and the key, never silently ignored,
// because a typo in a fault file would otherwise run a healthy plant.
#include "plant/core/scenario.h"

#include <cmath>
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
      // Tiny factors are accepted by "> 0" but make the wear a/D overflow (a
      // subnormal D gives an infinite resistance) and CVODE fail an interval
      // later, ending the plant mid-run (found by tests/fuzz/fuzz_scenario.cpp).
      // 1e-3 intervals already wears a component out within one control step.
      if (std::isnan(v[k]) || !(v[k] >= kMinFactor)) {
        std::ostringstream os;
        os << "element " << k << " must be > 0 and at least " << kMinFactor
           << " intervals (inf = healthy), got " << v[k];
        Fail(key, os.str());
      }
    }
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
    } else {
      r.Fail(key,
             "unknown key (known: name, tank_factor, engine_factor, degradation, "
             "steps_per_interval, [noise] std, [start] random)");
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
