// Scenario files: the shipped ones load; every malformed case in tests/data is
// a ScenarioError naming the file and the offending key.
#include <gtest/gtest.h>

#include <cmath>
#include <string>

#include "plant/core/scenario.h"

namespace ftc {
namespace {

std::string Source(const std::string& relative) {
  return std::string(FTC_SOURCE_DIR) + "/" + relative;
}

TEST(Scenario, ShippedScenariosLoad) {
  const FaultScenario nominal = LoadScenario(Source("scenarios/nominal.toml"));
  EXPECT_EQ(nominal.name, "nominal");
  EXPECT_TRUE(std::isinf(nominal.tank_factor.maxCoeff()));
  EXPECT_TRUE(std::isinf(nominal.engine_factor.minCoeff()));

  const FaultScenario single = LoadScenario(Source("scenarios/single.toml"));
  EXPECT_EQ(single.engine_factor[0], 20.0);
  EXPECT_TRUE(std::isinf(single.engine_factor[1]));
  EXPECT_EQ(single.mode, DegradationMode::kStepwise);
  EXPECT_EQ(single.steps_per_interval, 512);

  const FaultScenario multiple = LoadScenario(Source("scenarios/multiple.toml"));
  EXPECT_EQ(multiple.engine_factor[0], 20.0);
  EXPECT_EQ(multiple.tank_factor[4], 20.0);
  EXPECT_EQ(multiple.tank_factor[5], 20.0);
  EXPECT_TRUE(std::isinf(multiple.tank_factor[3]));

  const FaultScenario noisy = LoadScenario(Source("tests/data/noisy_multiple.toml"));
  EXPECT_EQ(noisy.noise_std, 0.01);
}

TEST(Scenario, AllKeysParse) {
  const FaultScenario s = ParseScenario(R"(
name = "everything"
tank_factor = [10, 20.5, inf, inf, inf, 30]
engine_factor = [inf, 15]
degradation = "continuous"
steps_per_interval = 64
[noise]
std = 0.02
[start]
random = true
)", "inline.toml");
  EXPECT_EQ(s.name, "everything");
  EXPECT_EQ(s.tank_factor[0], 10.0);  // integers are accepted as numbers
  EXPECT_EQ(s.tank_factor[1], 20.5);
  EXPECT_EQ(s.engine_factor[1], 15.0);
  EXPECT_EQ(s.mode, DegradationMode::kContinuous);
  EXPECT_EQ(s.steps_per_interval, 64);
  EXPECT_EQ(s.noise_std, 0.02);
  EXPECT_TRUE(s.random_start);
  // An empty file is the nominal plant.
  const FaultScenario empty = ParseScenario("", "empty.toml");
  EXPECT_TRUE(std::isinf(empty.tank_factor.minCoeff()));
  EXPECT_EQ(empty.noise_std, 0.0);
}

struct BadCase {
  const char* file;
  const char* key;
  const char* detail;  // a fragment the message must contain
};

class ScenarioErrors : public ::testing::TestWithParam<BadCase> {};

TEST_P(ScenarioErrors, NameTheFileAndTheKey) {
  const BadCase c = GetParam();
  const std::string path = Source(std::string("tests/data/") + c.file);
  try {
    LoadScenario(path);
    FAIL() << c.file << " was accepted";
  } catch (const ScenarioError& e) {
    const std::string msg = e.what();
    EXPECT_NE(msg.find(path), std::string::npos) << msg;
    EXPECT_NE(msg.find(std::string("key '") + c.key + "'"), std::string::npos) << msg;
    EXPECT_NE(msg.find(c.detail), std::string::npos) << msg;
  }
}

INSTANTIATE_TEST_SUITE_P(
    Malformed, ScenarioErrors,
    ::testing::Values(BadCase{"bad_length.toml", "tank_factor", "expected 6 numbers, got 5"},
                      BadCase{"bad_type.toml", "engine_factor", "got string"},
                      BadCase{"bad_zero.toml", "tank_factor", "must be > 0"},
                      BadCase{"bad_negative.toml", "engine_factor", "must be > 0"},
                      BadCase{"bad_nan.toml", "engine_factor", "must be > 0"},
                      BadCase{"bad_unknown_key.toml", "tank_factors", "unknown key"},
                      BadCase{"bad_degradation.toml", "degradation", "exponential"},
                      BadCase{"bad_noise.toml", "noise.std", ">= 0"},
                      BadCase{"bad_noise_key.toml", "noise.sigma", "unknown key"},
                      BadCase{"bad_element.toml", "tank_factor", "element 2 is a string"},
                      BadCase{"bad_steps.toml", "steps_per_interval", "positive"},
                      BadCase{"bad_start.toml", "start.random", "expected a boolean"}));

TEST(Scenario, SyntaxErrorsAndMissingFilesNameTheFile) {
  try {
    ParseScenario("tank_factor = [1, 2", "broken.toml");
    FAIL();
  } catch (const ScenarioError& e) {
    EXPECT_NE(std::string(e.what()).find("broken.toml:"), std::string::npos) << e.what();
  }
  EXPECT_THROW(LoadScenario(Source("tests/data/does_not_exist.toml")), ScenarioError);
}

}  // namespace
}  // namespace ftc
