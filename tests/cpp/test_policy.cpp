// The embedded controller's policy (cpp/policy/policy.h): its arithmetic on
// hand-made weights with known actions, the history window's order, and the
// checks that refuse bad ones.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <limits>
#include <random>
#include <sstream>

#include "policy/policy.h"
#include "policy/push_wire.h"

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
  EXPECT_NE(error.find("not an ftc-policy weights file"), std::string::npos) << error;
  EXPECT_FALSE(Policy::FromFile(::testing::TempDir() + "missing.txt", &error));
  EXPECT_NE(error.find("cannot open"), std::string::npos) << error;
}

// One dense layer from a window of 2 steps (24 inputs) to 6 logits that copies
// input `from + i` to logit i (W = a shifted identity, b = 0).
std::vector<float> Picks(int inputs, int from) {
  std::vector<float> p(static_cast<std::size_t>(inputs + 1) * 6, 0.0f);
  for (int i = 0; i < 6; ++i) p[static_cast<std::size_t>((from + i) * 6 + i)] = 1.0f;
  return p;
}

TEST(History, TheWindowIsNewestFirstLevelsThenValves) {
  // slot 0 is the input's first 12 floats (levels, then the valves commanded
  // before them), slot 1 the next 12: a policy reading slot 1's levels opens
  // where the tank was above half one step ago, one reading slot 0's valves
  // repeats the last command, one reading slot 0's levels looks at now
  std::string error;
  auto older = Policy::Make(2, {24, 6}, Picks(24, 12), 1, &error);
  auto command = Policy::Make(2, {24, 6}, Picks(24, 6), 1, &error);
  auto now = Policy::Make(2, {24, 6}, Picks(24, 0), 1, &error);
  ASSERT_TRUE(older && command && now) << error;
  History h;
  h.Start({0.2, 0.7, 0.2, 0.7, 0.2, 0.7});
  EXPECT_EQ(older->Act(h), (std::array<std::int8_t, 6>{0, 1, 0, 1, 0, 1}));
  EXPECT_EQ(command->Act(h), (std::array<std::int8_t, 6>{0, 0, 0, 0, 0, 0}));  // closed
  h.Push({0.9, 0.1, 0.9, 0.1, 0.9, 0.1}, {1, 1, 0, 0, 1, 0});
  EXPECT_EQ(now->Act(h), (std::array<std::int8_t, 6>{1, 0, 1, 0, 1, 0}));
  EXPECT_EQ(older->Act(h), (std::array<std::int8_t, 6>{0, 1, 0, 1, 0, 1}));
  EXPECT_EQ(command->Act(h), (std::array<std::int8_t, 6>{1, 1, 0, 0, 1, 0}));
  // around the ring many times: still the last two steps, in order
  for (int k = 0; k < 3 * kMaxWindow + 1; ++k)
    h.Push({0.2, 0.2, 0.2, 0.2, 0.2, 0.2}, {0, 0, 0, 0, 0, 0});
  h.Push({0.8, 0.8, 0.8, 0.8, 0.8, 0.8}, {0, 1, 0, 1, 0, 1});
  EXPECT_EQ(now->Act(h), (std::array<std::int8_t, 6>{1, 1, 1, 1, 1, 1}));
  EXPECT_EQ(older->Act(h), (std::array<std::int8_t, 6>{0, 0, 0, 0, 0, 0}));
  EXPECT_EQ(command->Act(h), (std::array<std::int8_t, 6>{0, 1, 0, 1, 0, 1}));
  // a new episode: every slot its first levels, the valves closed
  h.Start({0.6, 0.6, 0.6, 0.4, 0.4, 0.4});
  EXPECT_EQ(older->Act(h), (std::array<std::int8_t, 6>{1, 1, 1, 0, 0, 0}));
  EXPECT_EQ(command->Act(h), (std::array<std::int8_t, 6>{0, 0, 0, 0, 0, 0}));
}

TEST(History, TheStuckMemoryHoldsValvesAppliedAgainstTheirCommand) {
  // a window of 1 step and the memory (24 inputs): a policy reading the memory's
  // first six floats opens the valves seen stuck closed, one reading the next six
  // those seen stuck open
  std::string error;
  auto closed = Policy::Make(1, {24, 6}, Picks(24, 12), 1, &error, true);
  auto open = Policy::Make(1, {24, 6}, Picks(24, 18), 1, &error, true);
  ASSERT_TRUE(closed && open) << error;
  EXPECT_TRUE(closed->stuck_memory());
  History h;
  h.Start({0.5, 0.5, 0.5, 0.5, 0.5, 0.5});
  EXPECT_EQ(closed->Act(h), (std::array<std::int8_t, 6>{0, 0, 0, 0, 0, 0}));
  // valve 1 commanded open stayed closed, valve 3 commanded closed stayed open
  h.Push({0.4, 0.4, 0.4, 0.4, 0.4, 0.4}, {1, 1, 0, 0, 0, 0}, {0, 1, 1, 0, 0, 0});
  EXPECT_EQ(closed->Act(h), (std::array<std::int8_t, 6>{1, 0, 0, 0, 0, 0}));
  EXPECT_EQ(open->Act(h), (std::array<std::int8_t, 6>{0, 0, 1, 0, 0, 0}));
  // a new episode keeps it; a valve that follows its command says nothing; one
  // seen in the other state flips; the two-argument Push sees nothing
  h.Start({0.5, 0.5, 0.5, 0.5, 0.5, 0.5});
  h.Push({0.4, 0.4, 0.4, 0.4, 0.4, 0.4}, {0, 0, 0, 0, 0, 0}, {1, 0, 0, 0, 0, 0});
  h.Push({0.4, 0.4, 0.4, 0.4, 0.4, 0.4}, {1, 1, 1, 1, 1, 1});
  EXPECT_EQ(closed->Act(h), (std::array<std::int8_t, 6>{0, 0, 0, 0, 0, 0}));
  EXPECT_EQ(open->Act(h), (std::array<std::int8_t, 6>{1, 0, 1, 0, 0, 0}));
  h.Forget();
  EXPECT_EQ(open->Act(h), (std::array<std::int8_t, 6>{0, 0, 0, 0, 0, 0}));
  // the memory needs a window, and the window's width plus its 12
  EXPECT_FALSE(Policy::Make(0, {18, 6}, Picks(18, 0), 1, &error, true));
  EXPECT_EQ(error, "the stuck memory is read after a history window (window 0 given)");
  EXPECT_FALSE(Policy::Make(1, {12, 6}, Picks(12, 0), 1, &error, true));
  EXPECT_NE(error.find("from 24 (a window of 1 steps of levels and valves, then the stuck "
                       "memory)"), std::string::npos) << error;
}

TEST(Policy, ReadsAWeightsFileWithTheStuckMemory) {
  const auto p = Picks(24, 12);
  const std::vector<int> widths{24, 6};
  auto text = [&](std::uint64_t sum, const std::string& memory_line) {
    std::ostringstream out;
    out << "ftc-policy 2\nversion 7\nwindow 1\n" << memory_line << "widths 24 6\nparams "
        << p.size() << "\n";
    for (float v : p) out << v << " ";
    out << "\nchecksum " << std::hex << sum << "\n";
    return out.str();
  };
  std::string error;
  auto policy = Policy::FromFile(
      Write("m.txt", text(Checksum(widths, p, 1, true), "stuck_memory 1\n")), &error);
  ASSERT_TRUE(policy) << error;
  EXPECT_TRUE(policy->stuck_memory());
  // the checksum covers the memory: a file that drops its line, or keeps the
  // window's checksum, is refused; a value other than 0 or 1 is named
  EXPECT_NE(Checksum(widths, p, 1, true), Checksum(widths, p, 1));
  EXPECT_FALSE(Policy::FromFile(Write("m0.txt", text(Checksum(widths, p, 1, true), "")), &error));
  EXPECT_NE(error.find("checksum mismatch"), std::string::npos) << error;
  EXPECT_FALSE(Policy::FromFile(
      Write("m1.txt", text(Checksum(widths, p, 1), "stuck_memory 1\n")), &error));
  EXPECT_NE(error.find("checksum mismatch"), std::string::npos) << error;
  EXPECT_FALSE(Policy::FromFile(
      Write("m2.txt", text(Checksum(widths, p, 1, true), "stuck_memory 2\n")), &error));
  EXPECT_NE(error.find(":4: stuck_memory: 0 or 1 expected"), std::string::npos) << error;
}

TEST(History, ScalesAsNumPysFloat32) {
  // float32 first, clipped, 2 x - 1 in float32: 0.1 as float32 is
  // 0.100000001490116..., so the input is 2 * that - 1 rounded to float32
  std::array<float, 12> out{};
  History h;
  h.Start({0.1, -0.5, 1.5, 0.0, 1.0, 0.3});
  h.Newest(1, out.data());
  EXPECT_EQ(out[0], 2.0f * 0.1f - 1.0f);
  EXPECT_EQ(out[1], -1.0f);  // clipped to 0
  EXPECT_EQ(out[2], 1.0f);   // clipped to 1
  EXPECT_EQ(out[5], 2.0f * 0.3f - 1.0f);
  for (int i = 6; i < 12; ++i) EXPECT_EQ(out[i], -1.0f);
}

// One dense layer from a window of 1 step (12 inputs) to the joint head's 64
// logits: W = 0 and the biases `bias`, so the logits are the biases whatever
// the history.
std::unique_ptr<Policy> Joint(const std::vector<float>& bias, std::string* error) {
  std::vector<float> p(static_cast<std::size_t>(12 * kSettings), 0.0f);
  p.insert(p.end(), bias.begin(), bias.end());
  return Policy::Make(1, {12, kSettings}, p, 1, error);
}

TEST(Policy, TheJointHeadOpensTheBitsOfItsLargestLogitTheFirstOnTies) {
  std::string error;
  History h;
  h.Start({0.5, 0.5, 0.5, 0.5, 0.5, 0.5});
  std::vector<float> bias(kSettings, -1.0f);
  bias[37] = 2.0f;  // 37 = 0b100101: valves 0, 2 and 5
  auto policy = Joint(bias, &error);
  ASSERT_TRUE(policy) << error;
  EXPECT_EQ(policy->Act(h), (std::array<std::int8_t, 6>{1, 0, 1, 0, 0, 1}));
  // every setting maps to its own bits (valve i = bit i, not reversed)
  for (int a = 0; a < kSettings; ++a) {
    std::vector<float> one(kSettings, 0.0f);
    one[a] = 1.0f;
    const auto u = Policy::JointValves(one.data());
    int back = 0;
    for (int i = 0; i < 6; ++i) back |= u[i] << i;
    EXPECT_EQ(back, a);
  }
  // a tie between 6 (0b000110) and 48 (0b110000): the first, as torch's argmax
  bias.assign(kSettings, 0.0f);
  bias[48] = bias[6] = 3.0f;
  policy = Joint(bias, &error);
  ASSERT_TRUE(policy) << error;
  EXPECT_EQ(policy->Act(h), (std::array<std::int8_t, 6>{0, 1, 1, 0, 0, 0}));
  bias.assign(kSettings, 0.5f);  // all equal: setting 0, every valve closed
  EXPECT_EQ(Policy::JointValves(bias.data()), (std::array<std::int8_t, 6>{0, 0, 0, 0, 0, 0}));
  bias.back() = 0.75f;  // the last largest: all open
  EXPECT_EQ(Policy::JointValves(bias.data()), (std::array<std::int8_t, 6>{1, 1, 1, 1, 1, 1}));
}

TEST(Policy, AnOutputWidthOtherThanSixOrSixtyFourIsRefused) {
  std::string error;
  for (int out : {1, 7, 32, 63, 65, 128}) {
    std::vector<float> p(static_cast<std::size_t>(13 * out), 0.0f);
    EXPECT_FALSE(Policy::Make(1, {12, out}, p, 1, &error)) << out;
    EXPECT_EQ(error, "widths must run from 12 (a window of 1 steps of levels and valves) to 6 "
                     "(a logit per valve) or 64 (a logit per valve setting)");
  }
}

TEST(Policy, AWindowNeedsItsInputWidth) {
  std::string error;
  EXPECT_FALSE(Policy::Make(12, {6, 6}, Identity(), 1, &error));
  EXPECT_EQ(error, "widths must run from 144 (a window of 12 steps of levels and valves) to 6 "
                   "(a logit per valve) or 64 (a logit per valve setting)");
  EXPECT_FALSE(Policy::Make(kMaxWindow + 1, {6, 6}, Identity(), 1, &error));
  EXPECT_NE(error.find("a window of 257 steps (allowed: 0..256)"), std::string::npos) << error;
  EXPECT_FALSE(Policy::Make(-1, {6, 6}, Identity(), 1, &error));
}

TEST(Policy, ReadsAWindowedWeightsFile) {
  const auto p = Picks(24, 12);
  const std::vector<int> widths{24, 6};
  auto text = [&](std::uint64_t sum, const std::string& window_line) {
    std::ostringstream out;
    out << "ftc-policy 2\nversion 7\n" << window_line << "widths 24 6\nparams " << p.size()
        << "\n";
    for (float v : p) out << v << " ";
    out << "\nchecksum " << std::hex << sum << "\n";
    return out.str();
  };
  std::string error;
  auto policy = Policy::FromFile(Write("w.txt", text(Checksum(widths, p, 2), "window 2\n")),
                                 &error);
  ASSERT_TRUE(policy) << error;
  EXPECT_EQ(policy->window(), 2);
  EXPECT_EQ(policy->version(), 7);
  // the checksum covers the window, and the policy_t checksum is not accepted
  EXPECT_NE(Checksum(widths, p, 2), Checksum(widths, p, 3));
  EXPECT_FALSE(Policy::FromFile(Write("w3.txt", text(Checksum(widths, p, 2), "window 3\n")),
                                &error));
  EXPECT_NE(error.find("checksum mismatch"), std::string::npos) << error;
  EXPECT_FALSE(Policy::FromFile(Write("w1.txt", text(Checksum(widths, p), "window 2\n")), &error));
  EXPECT_NE(error.find("checksum mismatch"), std::string::npos) << error;
  EXPECT_FALSE(Policy::FromFile(Write("w0.txt", text(Checksum(widths, p, 2), "")), &error));
  EXPECT_NE(error.find("no window line"), std::string::npos) << error;
}

// A 6-12-12-6 policy whose middle layer is block-diagonal with `blocks` blocks
// (the shape of an ensemble of that many members), its other weights dense;
// every weight is drawn from [-1, 1] by a fixed generator. `leak` puts one
// nonzero weight outside the blocks.
std::vector<float> BlockWeights(int blocks, bool leak) {
  std::mt19937 rng(5);
  std::uniform_real_distribution<float> u(-1.0f, 1.0f);
  std::vector<float> p;
  for (int i = 0; i < 7 * 12; ++i) p.push_back(u(rng));  // W1 (6 x 12), b1
  const int b = 12 / blocks;
  for (int r = 0; r < 12; ++r)
    for (int c = 0; c < 12; ++c) p.push_back(r / b == c / b ? u(rng) : 0.0f);  // W2
  for (int c = 0; c < 12; ++c) p.push_back(u(rng));  // b2
  if (leak) p[7 * 12 + 0 * 12 + 11] = 0.25f;  // W2 row 0, column 11: off every block
  for (int i = 0; i < 13 * 6; ++i) p.push_back(u(rng));  // W3 (12 x 6), b3
  return p;
}

// The logits of the 6-12-12-6 chain in double precision, dense.
std::array<double, 6> DenseLogits(const std::vector<float>& p, const std::array<double, 6>& level) {
  std::vector<double> x(level.begin(), level.end());
  for (double& v : x) v = 2.0 * static_cast<double>(static_cast<float>(v)) - 1.0;
  const int widths[] = {6, 12, 12, 6};
  std::size_t at = 0;
  for (int l = 0; l < 3; ++l) {
    const int in = widths[l], out = widths[l + 1];
    std::vector<double> z(static_cast<std::size_t>(out));
    for (int c = 0; c < out; ++c) {
      double sum = p[at + static_cast<std::size_t>(in * out + c)];
      for (int r = 0; r < in; ++r) sum += x[r] * p[at + static_cast<std::size_t>(r * out + c)];
      z[c] = l < 2 ? std::tanh(sum) : sum;
    }
    at += static_cast<std::size_t>((in + 1) * out);
    x = z;
  }
  std::array<double, 6> logits{};
  std::copy(x.begin(), x.end(), logits.begin());
  return logits;
}

TEST(Policy, ABlockDiagonalLayerIsFlownAsItsBlocksWithTheDenseLayersActions) {
  for (const int blocks : {2, 3, 6}) {
    for (const bool leak : {false, true}) {
      const auto p = BlockWeights(blocks, leak);
      std::string error;
      auto policy = Policy::Make({6, 12, 12, 6}, p, 1, &error);
      ASSERT_TRUE(policy) << error;
      // the most blocks the zeros allow; one weight off the blocks makes it dense
      EXPECT_EQ(policy->blocks(), (std::vector<int>{1, leak ? 1 : blocks, 1})) << blocks;
      std::mt19937 rng(blocks);
      std::uniform_real_distribution<double> u(0.0, 1.0);
      int compared = 0;
      for (int trial = 0; trial < 500; ++trial) {
        std::array<double, 6> level{};
        for (double& v : level) v = u(rng);
        const auto logits = DenseLogits(p, level);
        const auto act = policy->Act(level);
        for (int i = 0; i < 6; ++i) {
          // float32 against double: the logits (of order 1) agree to ~1e-6;
          // a sign is compared only where it is farther than 1e-4 from zero
          if (std::abs(logits[i]) < 1e-4) continue;
          EXPECT_EQ(act[i], logits[i] > 0 ? 1 : 0) << blocks << " " << trial << " " << i;
          ++compared;
        }
      }
      EXPECT_GT(compared, 2900);
    }
  }
}

// The logits of a dense tanh chain of `widths` (the last layer linear) on
// `x`, in double precision: the reference the float32 paths are held to.
std::vector<double> ChainLogits(const std::vector<int>& widths, const std::vector<float>& p,
                                std::vector<double> x) {
  std::size_t at = 0;
  for (std::size_t l = 0; l + 1 < widths.size(); ++l) {
    const int in = widths[l], out = widths[l + 1];
    std::vector<double> z(static_cast<std::size_t>(out));
    for (int c = 0; c < out; ++c) {
      double sum = p[at + static_cast<std::size_t>(in * out + c)];
      for (int r = 0; r < in; ++r) sum += x[r] * p[at + static_cast<std::size_t>(r * out + c)];
      z[c] = l + 2 < widths.size() ? std::tanh(sum) : sum;
    }
    at += static_cast<std::size_t>((in + 1) * out);
    x = z;
  }
  return x;
}

// Flies `prepared` (Prepare after every step, a warm-up before every other
// one) and `whole` (neither) on one random history of 3,000 steps, with new
// episodes and double pushes among them, and holds both to the double-precision
// logits. Returns how many steps had Prepare's sums ready for them (the step
// before prepared them and exactly one push followed).
std::int64_t FlyPreparedAndWhole(Policy* prepared, Policy* whole, const std::vector<int>& widths,
                                 const std::vector<float>& p, std::mt19937* rng) {
  const int window = prepared->window();
  const int inputs = widths.front();
  History h;
  std::uniform_real_distribution<double> level(0.0, 1.0);
  auto levels = [&] {
    std::array<double, kTanks> l{};
    for (double& v : l) v = level(*rng);
    return l;
  };
  auto valves = [&] {
    std::array<std::int8_t, kTanks> v{};
    for (auto& b : v) b = static_cast<std::int8_t>((*rng)() & 1);
    return v;
  };
  prepared->Warm();  // before anything was acted on: changes nothing below
  h.Start(levels());
  std::int64_t ready_steps = 0, compared = 0;
  bool ready = false;
  for (int step = 0; step < 3000; ++step) {
    const auto kind = (*rng)() % 20;
    if (kind == 0) {  // a new episode: the sums are of another history
      h.Start(levels());
      ready = false;
    } else if (kind == 1) {  // two pushes after Prepare: the sums are a step behind
      h.Push(levels(), valves(), valves());
      h.Push(levels(), valves(), valves());
      ready = false;
    } else {
      h.Push(levels(), valves(), valves());  // (applied valves at random: stuck memory moves)
    }
    ready_steps += ready;
    if (step % 2) prepared->Warm();  // the node's warm-up: changes nothing the Act computes
    const auto a = prepared->Act(h);
    const auto b = whole->Act(h);
    std::vector<float> x(static_cast<std::size_t>(inputs));
    h.Newest(window, x.data());
    if (prepared->stuck_memory()) h.Memory(x.data() + kStepFeatures * window);
    const auto logits = ChainLogits(widths, p, std::vector<double>(x.begin(), x.end()));
    for (int i = 0; i < kTanks; ++i) {
      // float32 against double: logits of order 1 agree to ~1e-6; a sign is
      // compared where it is farther than 1e-4 from zero
      if (std::abs(logits[i]) < 1e-4) continue;
      EXPECT_EQ(a[i], logits[i] > 0 ? 1 : 0) << step << " " << i;
      EXPECT_EQ(b[i], a[i]) << step << " " << i;
      ++compared;
    }
    prepared->Prepare(h);
    ready = true;
  }
  EXPECT_GT(compared, 17000);
  EXPECT_EQ(whole->prepared_acts(), 0);
  return ready_steps;
}

TEST(Policy, APreparedStepHasTheWholeLayersActionsAndIsUsedForTheNextPushOnly) {
  // (and a warm-up between changes neither). Windows of 4 with the stuck
  // memory (60 inputs) and without (48), 16 tanh units, the valves head;
  // weights from [-1, 1] by a fixed generator.
  for (const bool memory : {true, false}) {
    const std::vector<int> widths{memory ? 60 : 48, 16, 6};
    std::mt19937 rng(memory ? 11 : 12);
    std::uniform_real_distribution<float> u(-1.0f, 1.0f);
    std::vector<float> p(static_cast<std::size_t>((widths[0] + 1) * 16 + (16 + 1) * 6));
    for (float& v : p) v = u(rng);
    std::string error;
    auto prepared = Policy::Make(4, widths, p, 1, &error, memory);
    auto whole = Policy::Make(4, widths, p, 1, &error, memory);
    ASSERT_TRUE(prepared && whole) << error;
    const auto ready = FlyPreparedAndWhole(prepared.get(), whole.get(), widths, p, &rng);
    EXPECT_EQ(prepared->prepared_acts(), ready) << memory;
    EXPECT_GT(ready, 2400) << memory;  // about 0.9 of the steps
  }
}

TEST(Policy, PreparedSumsServeOnlyTheStepsTheyWereTakenOf) {
  // 48-16-6, window 4, no memory
  const std::vector<int> widths{48, 16, 6};
  std::mt19937 rng(13);
  std::uniform_real_distribution<float> u(-1.0f, 1.0f);
  std::vector<float> p(static_cast<std::size_t>(49 * 16 + 17 * 6));
  for (float& v : p) v = u(rng);
  std::string error;
  auto policy = Policy::Make(4, widths, p, 1, &error);
  auto whole = Policy::Make(4, widths, p, 1, &error);
  ASSERT_TRUE(policy && whole) << error;
  // another history, one push after as many pushes as the prepared one: the
  // whole layer runs, with the whole layer's actions
  History a, b;
  a.Start({0.1, 0.2, 0.3, 0.4, 0.5, 0.6});
  b.Start({0.6, 0.5, 0.4, 0.3, 0.2, 0.1});
  policy->Prepare(a);
  b.Push({0.2, 0.2, 0.2, 0.8, 0.8, 0.8}, {1, 1, 1, 0, 0, 0});
  EXPECT_EQ(policy->Act(b), whole->Act(b));
  EXPECT_EQ(policy->prepared_acts(), 0);
  a.Push({0.2, 0.2, 0.2, 0.8, 0.8, 0.8}, {1, 1, 1, 0, 0, 0});
  EXPECT_EQ(policy->Act(a), whole->Act(a));
  EXPECT_EQ(policy->prepared_acts(), 1);
  // nothing to prepare for a window of 1, or for a first layer of blocks
  auto one = Policy::Make(1, {12, 6}, std::vector<float>(13 * 6, 0.5f), 1, &error);
  ASSERT_TRUE(one) << error;
  one->Prepare(a);
  a.Push({0.3, 0.3, 0.3, 0.3, 0.3, 0.3}, {0, 0, 0, 0, 0, 0});
  one->Act(a);
  EXPECT_EQ(one->prepared_acts(), 0);
  std::vector<float> blocks(static_cast<std::size_t>(49 * 16 + 17 * 6), 0.0f);
  for (int r = 0; r < 48; ++r)  // two blocks of 24 x 8: rows 0-23 to units 0-7, 24-47 to 8-15
    for (int c = 0; c < 16; ++c)
      if (r / 24 == c / 8) blocks[static_cast<std::size_t>(r * 16 + c)] = u(rng);
  for (std::size_t i = 48 * 16; i < blocks.size(); ++i) blocks[i] = u(rng);
  auto split = Policy::Make(4, widths, blocks, 1, &error);
  ASSERT_TRUE(split) << error;
  EXPECT_EQ(split->blocks(), (std::vector<int>{2, 1}));
  split->Prepare(a);
  a.Push({0.4, 0.4, 0.4, 0.4, 0.4, 0.4}, {1, 1, 1, 1, 1, 1});
  split->Act(a);
  EXPECT_EQ(split->prepared_acts(), 0);
}

TEST(PushWire, APolicyV2IsCheckedBeforeDecodingAndToldFromAPolicyT) {
  policy_v2_t m{};
  m.version = 3;
  m.window = 2;
  m.num_widths = 2;
  m.widths = {24, 6};
  m.params = Picks(24, 12);
  m.num_params = static_cast<std::int32_t>(m.params.size());
  std::vector<unsigned char> buf(static_cast<std::size_t>(m.getEncodedSize()));
  m.encode(buf.data(), 0, static_cast<int>(buf.size()));
  policy_v2_t out{};
  std::string why;
  ASSERT_TRUE(DecodePolicyV2(buf.data(), buf.size(), &out, &why)) << why;
  EXPECT_EQ(out.window, 2);
  EXPECT_EQ(out.params, m.params);
  EXPECT_TRUE(IsPolicyV2(buf.data(), buf.size()));
  EXPECT_EQ(out.stuck_memory, 0);
  // num_params (after the fingerprint, utime, version, window, stuck_memory,
  // num_widths and the widths) declared as 250 million: refused by the count,
  // nothing allocated
  const std::size_t at = 8 + 8 + 8 + 4 + 1 + 4 + 2 * 4;
  std::vector<unsigned char> hostile(buf.begin(), buf.begin() + static_cast<long>(at) + 4);
  hostile[at] = 0x0e;
  hostile[at + 1] = 0xe6;
  hostile[at + 2] = 0xb2;
  hostile[at + 3] = 0x80;
  EXPECT_FALSE(DecodePolicyV2(hostile.data(), hostile.size(), &out, &why));
  EXPECT_EQ(why, "num_params is 250000000 (allowed: 0..524288)");
  EXPECT_FALSE(DecodePolicyV2(buf.data(), buf.size() - 1, &out, &why));
  policy_t old{};
  old.num_widths = 2;
  old.widths = {6, 6};
  old.params = Identity();
  old.num_params = static_cast<std::int32_t>(old.params.size());
  std::vector<unsigned char> v1(static_cast<std::size_t>(old.getEncodedSize()));
  old.encode(v1.data(), 0, static_cast<int>(v1.size()));
  EXPECT_FALSE(IsPolicyV2(v1.data(), v1.size()));
  EXPECT_FALSE(IsPolicyV2(v1.data(), 4));  // shorter than a fingerprint
}

}  // namespace
}  // namespace ftc::policy
