// Bounded decoding (cpp/plant/lcm/wire.h): the hostile lengths that crashed
// the policy node and lcm_echo are refused with a reason before lcm-gen's
// decoder runs; every well-formed message of random content passes (no false
// refusal); and a short fuzz run (seeded mutations of valid messages, the
// property of tests/fuzz/wire_harness.h) finds nothing. The long run is
// libFuzzer's, scripts/fuzz.sh.
#include <gtest/gtest.h>

#include <cstdint>
#include <random>
#include <string>
#include <vector>

#include "plant/lcm/wire.h"
#include "wire_harness.h"

namespace ftc {
namespace {

template <typename T>
std::vector<std::uint8_t> Encode(const T& msg) {
  std::vector<std::uint8_t> out(static_cast<std::size_t>(msg.getEncodedSize()));
  EXPECT_EQ(msg.encode(out.data(), 0, static_cast<int>(out.size())),
            static_cast<int>(out.size()));
  return out;
}

void PutBigEndian(std::vector<std::uint8_t>* buf, std::size_t at, std::uint64_t v, int n) {
  for (int i = 0; i < n; ++i)
    (*buf)[at + static_cast<std::size_t>(i)] = static_cast<std::uint8_t>(v >> (8 * (n - 1 - i)));
}

std::vector<std::uint8_t> Fingerprint(std::int64_t hash) {
  std::vector<std::uint8_t> out(8);
  PutBigEndian(&out, 0, static_cast<std::uint64_t>(hash), 8);
  return out;
}

plant_state_t State(std::mt19937_64* rng) {
  plant_state_t s{};
  s.seq = static_cast<std::int64_t>((*rng)());
  s.session = static_cast<std::int64_t>((*rng)());
  s.num_tanks = 6;
  s.num_engines = 2;
  s.level.assign(6, 0.25);
  s.true_level.assign(6, 0.5);
  s.valve.assign(6, 1);
  s.deficit.assign(2, 0.0);
  s.terminal = true;
  return s;
}

policy_t Policy(std::mt19937_64* rng, int layers) {
  policy_t p{};
  p.version = static_cast<std::int64_t>((*rng)());
  p.num_widths = layers;
  p.widths.assign(static_cast<std::size_t>(layers), 6);
  p.num_params = static_cast<std::int32_t>((*rng)() % 100);
  p.params.assign(static_cast<std::size_t>(p.num_params), 0.5f);
  return p;
}

// The crashes, each one message: refused, with the field named.
TEST(Wire, HostileLengthsAreRefusedBeforeDecoding) {
  std::mt19937_64 rng(1);
  {  // plant_state_t with num_tanks = -1 (std::length_error in the policy node)
    auto buf = Encode(State(&rng));
    buf[8 + 8 * 4 + 4 + 4 + 8 + 8] = 0xff;
    plant_state_t out;
    std::string why;
    EXPECT_FALSE(wire::Decode(buf.data(), buf.size(), &out, &why));
    EXPECT_NE(why.find("num_tanks -1"), std::string::npos) << why;
  }
  {  // valve_command_t with num_valves = -1 (lcm_echo aborted)
    valve_command_t cmd{};
    cmd.num_valves = 6;
    cmd.valve.assign(6, 0);
    auto buf = Encode(cmd);
    buf[8 + 8 * 4] = 0xff;
    std::string why;
    EXPECT_FALSE(wire::Decode(buf.data(), buf.size(), &cmd, &why));
    // (named as out of the schema's range, not only as longer than the message)
    EXPECT_NE(why.find("num_valves is -1 (allowed: 0..127)"), std::string::npos) << why;
  }
  const auto policy_with = [](std::uint32_t widths, std::uint32_t params, std::size_t size) {
    auto buf = Fingerprint(policy_t::getHash());
    buf.resize(size, 0);
    PutBigEndian(&buf, 24, widths, 4);  // after utime, version
    if (widths == 0) PutBigEndian(&buf, 28, params, 4);
    return buf;
  };
  policy_t p;
  std::string why;
  // num_widths = -1 (std::length_error)
  auto buf = policy_with(0xffffffffu, 0, 64);
  EXPECT_FALSE(wire::Decode(buf.data(), buf.size(), &p, &why));
  EXPECT_NE(why.find("num_widths is -1 (allowed: 0..65)"), std::string::npos) << why;
  // 36 bytes declaring 0x20000001 widths: lcm-gen's int product overflows (SIGSEGV)
  buf = policy_with(0x20000001u, 0, 36);
  EXPECT_FALSE(wire::Decode(buf.data(), buf.size(), &p, &why));
  EXPECT_NE(why.find("num_widths is 536870913"), std::string::npos) << why;
  // 40 bytes declaring 250,000,000 params (a 1 GB allocation)
  buf = policy_with(0, 250000000u, 40);
  EXPECT_FALSE(wire::Decode(buf.data(), buf.size(), &p, &why));
  EXPECT_NE(why.find("num_params is 250000000"), std::string::npos) << why;
  // within the schema's bound but longer than the message
  buf = policy_with(0, 1000, 40);
  EXPECT_FALSE(wire::Decode(buf.data(), buf.size(), &p, &why));
  EXPECT_NE(why.find("needs 4000 bytes"), std::string::npos) << why;
}

TEST(Wire, WrongTypeTruncationAndTailAreRefused) {
  std::mt19937_64 rng(2);
  const auto state = Encode(State(&rng));
  valve_command_t cmd;
  std::string why;
  EXPECT_FALSE(wire::Decode(state.data(), state.size(), &cmd, &why));
  EXPECT_NE(why.find("fingerprint"), std::string::npos) << why;
  plant_state_t s;
  for (std::size_t n = 0; n < state.size(); ++n) {
    EXPECT_FALSE(wire::Decode(state.data(), n, &s, &why)) << n;
    EXPECT_FALSE(why.empty());
  }
  auto longer = state;
  longer.push_back(0);
  EXPECT_FALSE(wire::Decode(longer.data(), longer.size(), &s, &why));
  EXPECT_NE(why.find("1 bytes after the end"), std::string::npos) << why;
}

// No false refusal: any well-formed message of each type decodes to itself.
TEST(Wire, EveryWellFormedMessagePasses) {
  std::mt19937_64 rng(3);
  for (int k = 0; k < 200; ++k) {
    plant_state_t s = State(&rng);
    const int tanks = static_cast<int>(rng() % 128), engines = static_cast<int>(rng() % 128);
    s.num_tanks = static_cast<std::int8_t>(tanks);
    s.num_engines = static_cast<std::int8_t>(engines);
    s.level.assign(static_cast<std::size_t>(tanks), 0.1);
    s.true_level.assign(static_cast<std::size_t>(tanks), 0.2);
    s.valve.assign(static_cast<std::size_t>(tanks), 1);
    s.deficit.assign(static_cast<std::size_t>(engines), 0.3);
    auto buf = Encode(s);
    plant_state_t out;
    std::string why;
    ASSERT_TRUE(wire::Decode(buf.data(), buf.size(), &out, &why)) << why;
    EXPECT_EQ(out.seq, s.seq);
    EXPECT_EQ(out.session, s.session);
    EXPECT_EQ(out.deficit, s.deficit);

    valve_command_t c{};
    c.seq = static_cast<std::int64_t>(rng());
    c.num_valves = static_cast<std::int8_t>(rng() % 128);
    c.valve.assign(static_cast<std::size_t>(c.num_valves), 1);
    buf = Encode(c);
    valve_command_t c2;
    ASSERT_TRUE(wire::Decode(buf.data(), buf.size(), &c2, &why)) << why;
    EXPECT_EQ(c2.valve, c.valve);

    plant_control_t m{};
    m.operating_step = static_cast<std::int64_t>(rng());
    m.command = static_cast<std::int8_t>(rng());
    buf = Encode(m);
    plant_control_t m2;
    ASSERT_TRUE(wire::Decode(buf.data(), buf.size(), &m2, &why)) << why;
    EXPECT_EQ(m2.operating_step, m.operating_step);

    policy_t p = Policy(&rng, static_cast<int>(rng() % (policy_t::MAX_WIDTHS + 1)));
    buf = Encode(p);
    policy_t p2;
    ASSERT_TRUE(wire::Decode(buf.data(), buf.size(), &p2, &why)) << why;
    EXPECT_EQ(p2.params, p.params);
  }
  // the schema's largest policy passes; one more parameter does not
  policy_t big = Policy(&rng, 2);
  big.num_params = policy_t::MAX_PARAMS;
  big.params.assign(static_cast<std::size_t>(big.num_params), 0.0f);
  auto buf = Encode(big);
  policy_t out;
  std::string why;
  EXPECT_TRUE(wire::Decode(buf.data(), buf.size(), &out, &why)) << why;
  big.num_params += 1;
  big.params.push_back(0.0f);
  buf = Encode(big);
  EXPECT_FALSE(wire::Decode(buf.data(), buf.size(), &out, &why));
}

// Mutations of valid encodings: byte flips, hostile counts written over each
// position, truncations and extensions; the harness aborts on a violation.
template <typename T>
std::size_t ShortFuzz(const std::vector<std::uint8_t>& seed, std::uint64_t rng_seed, int runs) {
  std::mt19937_64 rng(rng_seed);
  const std::uint32_t hostile[] = {0xffffffffu, 0x80000000u, 0x7fffffffu, 0x20000001u,
                                   250000000u,  0x01000000u, 1u << 20,    0xffu};
  std::size_t accepted = 0;
  for (int k = 0; k < runs; ++k) {
    std::vector<std::uint8_t> buf = seed;
    switch (rng() % 4) {
      case 0:
        for (int f = 0, n = 1 + static_cast<int>(rng() % 4); f < n; ++f)
          buf[rng() % buf.size()] ^= static_cast<std::uint8_t>(1u << (rng() % 8));
        break;
      case 1: {
        const std::size_t at = 8 + rng() % (buf.size() - 8);
        const std::uint32_t v = hostile[rng() % 8];
        for (int i = 0; i < 4 && at + static_cast<std::size_t>(i) < buf.size(); ++i)
          buf[at + static_cast<std::size_t>(i)] = static_cast<std::uint8_t>(v >> (24 - 8 * i));
        break;
      }
      case 2:
        buf.resize(rng() % buf.size());
        break;
      default:
        for (int i = 0, n = 1 + static_cast<int>(rng() % 16); i < n; ++i)
          buf.push_back(static_cast<std::uint8_t>(rng()));
    }
    ftc::fuzz::One<T>(buf.data(), buf.size());
    T out;
    std::string why;
    accepted += wire::Decode(buf.data(), buf.size(), &out, &why);
  }
  ftc::fuzz::One<T>(seed.data(), seed.size());
  return accepted;
}

TEST(Wire, ShortFuzzRunFindsNothing) {
  std::mt19937_64 rng(4);
  constexpr int kRuns = 40000;  // per type: ~0.1 s; libFuzzer runs millions (scripts/fuzz.sh)
  valve_command_t c{};
  c.num_valves = 6;
  c.valve.assign(6, 1);
  // some mutations must still be messages (flipped payload bits), or the
  // run only ever exercised the refusals
  EXPECT_GT(ShortFuzz<valve_command_t>(Encode(c), 10, kRuns), 0u);
  plant_control_t m{};
  EXPECT_GT(ShortFuzz<plant_control_t>(Encode(m), 11, kRuns), 0u);
  EXPECT_GT(ShortFuzz<plant_state_t>(Encode(State(&rng)), 12, kRuns), 0u);
  EXPECT_GT(ShortFuzz<policy_t>(Encode(Policy(&rng, 3)), 13, kRuns), 0u);
  policy_ack_t ack{};
  ack.reason = "version 1 is not above the running 2";
  EXPECT_GT(ShortFuzz<policy_ack_t>(Encode(ack), 14, kRuns), 0u);
}

TEST(Wire, RateLimitedLogPrintsABurstThenOneLineASecond) {
  wire::RateLimitedLog log("test");
  const auto t0 = wire::RateLimitedLog::Clock::time_point{} + std::chrono::hours(1);
  testing::internal::CaptureStderr();
  for (int i = 0; i < 100; ++i) log.Refused("x", t0 + std::chrono::milliseconds(i));
  log.Refused("y", t0 + std::chrono::milliseconds(1200));
  const std::string err = testing::internal::GetCapturedStderr();
  EXPECT_EQ(log.total(), 101);
  int lines = 0;
  for (char ch : err) lines += ch == '\n';
  EXPECT_EQ(lines, 11);  // 10 of the burst, then one after a second
  EXPECT_NE(err.find("test: y (90 more not logged)"), std::string::npos) << err;
}

}  // namespace
}  // namespace ftc
