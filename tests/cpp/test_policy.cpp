// The embedded controller's policy (cpp/policy/policy.h): its arithmetic on
// hand-made weights with known actions, and the checks that refuse bad ones.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <fstream>
#include <limits>
#include <sstream>

#include "policy/policy.h"

namespace ftc::policy {
namespace {

// One dense layer 6 -> 6, W = identity, b = 0: logit_i = 2 level_i - 1, so a
// valve opens exactly where its tank is more than half full.
std::vector<float> Identity() {
  std::vector<float> p(7 * 6, 0.0f);
  for (int i = 0; i < 6; ++i) p[i * 6 + i] = 1.0f;
  return p;
}

TEST(Policy, OneLinearLayerOpensTheValvesOfTanksAboveHalf) {
  std::string error;
  auto policy = Policy::Make({6, 6}, Identity(), 1, &error);
  ASSERT_TRUE(policy) << error;
  const auto u = policy->Act({0.2, 0.7, 0.49, 0.51, 1.0, 0.0});
  EXPECT_EQ(u, (std::array<std::int8_t, 6>{0, 1, 0, 1, 1, 0}));
}

TEST(Policy, HiddenLayersUseTanhAndTheLastLayerDoesNot) {
  // 6 -> 1 -> 6: hidden h = tanh(sum of inputs) (W1 all ones); the output
  // layer gives logit_i = h - 0.5 (W2 ones, b2 = -0.5). All tanks at 0.6: the
  // inputs sum to 1.2, tanh(1.2) = 0.83 > 0.5: open; all at 0.55: tanh(0.6) =
  // 0.54 > 0.5: open; all at 0.54: tanh(0.48) = 0.45: closed. Without the tanh
  // the last two would differ (0.6 and 0.48 against 0.5).
  std::vector<float> p;
  for (int i = 0; i < 6; ++i) p.push_back(1.0f);  // W1 (6 x 1)
  p.push_back(0.0f);                               // b1
  for (int i = 0; i < 6; ++i) p.push_back(1.0f);  // W2 (1 x 6)
  for (int i = 0; i < 6; ++i) p.push_back(-0.5f); // b2
  std::string error;
  auto policy = Policy::Make({6, 1, 6}, p, 1, &error);
  ASSERT_TRUE(policy) << error;
  EXPECT_EQ(policy->Act({0.6, 0.6, 0.6, 0.6, 0.6, 0.6})[0], 1);
  EXPECT_EQ(policy->Act({0.55, 0.55, 0.55, 0.55, 0.55, 0.55})[0], 1);
  EXPECT_EQ(policy->Act({0.54, 0.54, 0.54, 0.54, 0.54, 0.54})[0], 0);
}

TEST(Policy, RefusesWeightsThatDoNotFit) {
  std::string error;
  EXPECT_FALSE(Policy::Make({6, 5}, std::vector<float>(35), 1, &error));
  EXPECT_NE(error.find("from 6"), std::string::npos) << error;
  EXPECT_FALSE(Policy::Make({6, 6}, std::vector<float>(41), 1, &error));
  EXPECT_NE(error.find("41 parameters for layers that take 42"), std::string::npos) << error;
  auto p = Identity();
  p[3] = std::numeric_limits<float>::quiet_NaN();
  EXPECT_FALSE(Policy::Make({6, 6}, p, 1, &error));
  EXPECT_NE(error.find("parameter 3 is not finite"), std::string::npos) << error;
}

TEST(Policy, TheChecksumSeesEveryBitOfTheWeightsAndTheWidths) {
  auto p = Identity();
  const auto base = Checksum({6, 6}, p);
  EXPECT_EQ(base, Checksum({6, 6}, p));
  p[10] = std::nextafter(p[10], 1.0f);  // one ulp
  EXPECT_NE(base, Checksum({6, 6}, p));
  EXPECT_NE(base, Checksum({6, 7}, Identity()));
}

std::string WeightsText(const std::vector<float>& p, std::uint64_t checksum) {
  std::ostringstream out;
  out << "ftc-policy 1\nversion 4\nwidths 6 6\nparams " << p.size() << "\n";
  for (float v : p) out << v << " ";
  out << "\nchecksum " << std::hex << checksum << "\n";
  return out.str();
}

std::string Write(const std::string& name, const std::string& text) {
  const std::string path = ::testing::TempDir() + name;
  std::ofstream(path) << text;
  return path;
}

TEST(Policy, ReadsAWeightsFileAndNamesWhatIsWrongWithABadOne) {
  const auto p = Identity();
  std::string error;
  auto policy = Policy::FromFile(Write("good.txt", WeightsText(p, Checksum({6, 6}, p))), &error);
  ASSERT_TRUE(policy) << error;
  EXPECT_EQ(policy->version(), 4);
  EXPECT_EQ(policy->Act({0.2, 0.7, 0.2, 0.7, 0.2, 0.7})[1], 1);

  EXPECT_FALSE(Policy::FromFile(Write("sum.txt", WeightsText(p, 99)), &error));
  EXPECT_NE(error.find("checksum mismatch"), std::string::npos) << error;
  auto text = WeightsText(p, Checksum({6, 6}, p));
  EXPECT_FALSE(Policy::FromFile(Write("cut.txt", text.substr(0, text.size() / 2)), &error));
  EXPECT_NE(error.find("cut.txt"), std::string::npos) << error;
  EXPECT_FALSE(Policy::FromFile(Write("other.txt", "hello\n"), &error));
  EXPECT_NE(error.find("not an ftc-policy 1"), std::string::npos) << error;
  EXPECT_FALSE(Policy::FromFile(::testing::TempDir() + "missing.txt", &error));
  EXPECT_NE(error.find("cannot open"), std::string::npos) << error;
}

}  // namespace
}  // namespace ftc::policy
