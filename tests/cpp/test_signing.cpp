// Message authentication (plant/lcm/signing.h): HMAC-SHA256 against RFC 4231's
// published vectors; a signed message verifies, and a tampered byte, another
// channel, a replay, a stale timestamp, a missing trailer or another key are
// refused; a key file others can read is refused.
#include <gtest/gtest.h>

#include <sys/stat.h>
#include <unistd.h>

#include <cstdint>
#include <cstdio>
#include <fstream>
#include <string>
#include <vector>

#include "plant/lcm/signing.h"

namespace ftc::signing {
namespace {

std::string Hex(const unsigned char* p, std::size_t n) {
  static const char* digits = "0123456789abcdef";
  std::string out;
  for (std::size_t i = 0; i < n; ++i) {
    out += digits[p[i] >> 4];
    out += digits[p[i] & 15];
  }
  return out;
}

std::string Mac(const Key& key, const std::string& data) {
  const auto d = HmacSha256(key, reinterpret_cast<const unsigned char*>(data.data()), data.size());
  return Hex(d.data(), d.size());
}

TEST(Signing, HmacSha256MatchesRfc4231) {
  // Test Case 1: key 0x0b x 20, "Hi There"
  EXPECT_EQ(Mac(Key(20, 0x0b), "Hi There"),
            "b0344c61d8db38535ca8afceaf0bf12b881dc200c9833da726e9376c2e32cff7");
  // Test Case 2: key "Jefe"
  EXPECT_EQ(Mac(Key{'J', 'e', 'f', 'e'}, "what do ya want for nothing?"),
            "5bdcc146bf60754e6a042426089575c75a003f089d2739839dec58b964ec3843");
  // Test Case 3: key 0xaa x 20, data 0xdd x 50
  EXPECT_EQ(Mac(Key(20, 0xaa), std::string(50, '\xdd')),
            "773ea91e36800e46854db8ebd09181a72959098b3ef8c122d9635514ced565fe");
}

std::string KeyedMac(Hmac& hmac, const std::string& a, const std::string& b = "") {
  const auto d = hmac.Of({{reinterpret_cast<const unsigned char*>(a.data()), a.size()},
                          {reinterpret_cast<const unsigned char*>(b.data()), b.size()}});
  return Hex(d.data(), d.size());
}

TEST(Signing, TheKeyedContextMatchesRfc4231MessageAfterMessage) {
  // one context, keyed once, for several messages (what Signer and Verifier do),
  // each given in pieces: the same MACs as RFC 4231's vectors
  Hmac one(Key(20, 0x0b));
  EXPECT_EQ(KeyedMac(one, "Hi There"),
            "b0344c61d8db38535ca8afceaf0bf12b881dc200c9833da726e9376c2e32cff7");
  EXPECT_EQ(KeyedMac(one, "Hi ", "There"),
            "b0344c61d8db38535ca8afceaf0bf12b881dc200c9833da726e9376c2e32cff7");
  Hmac jefe(Key{'J', 'e', 'f', 'e'});
  EXPECT_EQ(KeyedMac(jefe, "what do ya want ", "for nothing?"),
            "5bdcc146bf60754e6a042426089575c75a003f089d2739839dec58b964ec3843");
  // Test Case 6: a key longer than SHA-256's block (hashed first)
  Hmac large(Key(131, 0xaa));
  EXPECT_EQ(KeyedMac(large, "Test Using Larger Than Block-Size Key - Hash Key First"),
            "60e431591ee0b67f0d8a26aacbf5b77f8e0bc6213728c5140546040f0ee37f54");
  EXPECT_EQ(KeyedMac(one, "Hi There"),  // the first context again, after the others
            "b0344c61d8db38535ca8afceaf0bf12b881dc200c9833da726e9376c2e32cff7");
}

const Key kKey(32, 0x42);
const std::string kChannel = "RUN_COMMAND";
const std::vector<unsigned char> kPayload{1, 2, 3, 4, 5, 6, 7, 8, 9};
constexpr std::int64_t kNow = 1'760'000'000'000'000;  // us since the epoch

TEST(Signing, ASignedMessageVerifiesOnceAndOnlyAsSent) {
  Signer signer(kKey, 7);
  const auto msg = signer.Sign(kChannel, kPayload.data(), kPayload.size(), kNow);
  ASSERT_EQ(msg.size(), kPayload.size() + kTrailerBytes);
  std::size_t n = 0;
  {
    Verifier v(kKey, kDefaultWindowUs, 0);
    EXPECT_EQ(v.Verify(kChannel, msg.data(), msg.size(), kNow, &n), Verdict::kOk);
    EXPECT_EQ(n, kPayload.size());
    // the same bytes again: a replay
    EXPECT_EQ(v.Verify(kChannel, msg.data(), msg.size(), kNow, &n), Verdict::kReplay);
  }
  for (std::size_t i = 0; i < msg.size(); ++i) {  // any tampered byte
    auto bad = msg;
    bad[i] ^= 0x01;
    Verifier v(kKey, kDefaultWindowUs, 0);
    EXPECT_EQ(v.Verify(kChannel, bad.data(), bad.size(), kNow, &n), Verdict::kBadSignature) << i;
  }
  Verifier v(kKey, kDefaultWindowUs, 0);
  EXPECT_EQ(v.Verify("RUN_CONTROL", msg.data(), msg.size(), kNow, &n), Verdict::kBadSignature);
  EXPECT_EQ(v.Verify(kChannel, kPayload.data(), kPayload.size(), kNow, &n),
            Verdict::kBadSignature);  // unsigned
  Verifier other(Key(32, 0x43), kDefaultWindowUs, 0);
  EXPECT_EQ(other.Verify(kChannel, msg.data(), msg.size(), kNow, &n), Verdict::kBadSignature);
}

TEST(Signing, TimestampsRisePerLinkAndOldOnesAreStale) {
  Signer signer(kKey, 1);
  const auto first = signer.Sign(kChannel, kPayload.data(), kPayload.size(), kNow);
  const auto second = signer.Sign(kChannel, kPayload.data(), kPayload.size(), kNow);  // same clock
  std::size_t n = 0;
  Verifier v(kKey, 30'000'000, 0);
  EXPECT_EQ(v.Verify(kChannel, second.data(), second.size(), kNow, &n), Verdict::kOk);
  // the earlier one after the later: a replay, though never seen
  EXPECT_EQ(v.Verify(kChannel, first.data(), first.size(), kNow, &n), Verdict::kReplay);
  // another link keeps its own count
  Signer other(kKey, 2);
  const auto from_other = other.Sign(kChannel, kPayload.data(), kPayload.size(), kNow);
  EXPECT_EQ(v.Verify(kChannel, from_other.data(), from_other.size(), kNow, &n), Verdict::kOk);
  // older than the window (30 s) when it arrives: stale
  Signer late(kKey, 3);
  const auto old = late.Sign(kChannel, kPayload.data(), kPayload.size(), kNow);
  EXPECT_EQ(v.Verify(kChannel, old.data(), old.size(), kNow + 31'000'000, &n), Verdict::kStale);
  Signer in_time(kKey, 4);
  const auto fresh = in_time.Sign(kChannel, kPayload.data(), kPayload.size(), kNow);
  EXPECT_EQ(v.Verify(kChannel, fresh.data(), fresh.size(), kNow + 29'000'000, &n), Verdict::kOk);
}

TEST(Signing, WhatWasSignedBeforeTheReceiverStartedIsAReplay) {
  // a plant or node restarted with the same key file has seen no timestamp of
  // any link: its start time is every link's floor
  Signer signer(kKey, 5);
  const auto before = signer.Sign(kChannel, kPayload.data(), kPayload.size(), kNow);
  const auto after = signer.Sign(kChannel, kPayload.data(), kPayload.size(), kNow + 2'000);
  std::size_t n = 0;
  Verifier restarted(kKey, kDefaultWindowUs, kNow + 1'000);
  EXPECT_EQ(restarted.Verify(kChannel, before.data(), before.size(), kNow + 3'000, &n),
            Verdict::kReplay);
  EXPECT_EQ(restarted.Verify(kChannel, after.data(), after.size(), kNow + 3'000, &n),
            Verdict::kOk);
  // by default the floor is this process's start: a message signed now passes,
  // one signed before it started does not
  Signer now_signer(kKey, 6);
  const auto fresh =
      now_signer.Sign(kChannel, kPayload.data(), kPayload.size(), WallMicros());
  Verifier v(kKey);
  EXPECT_EQ(v.Verify(kChannel, fresh.data(), fresh.size(), WallMicros(), &n), Verdict::kOk);
  EXPECT_EQ(v.Verify(kChannel, after.data(), after.size(), kNow + 3'000, &n), Verdict::kReplay);
  EXPECT_LE(kProcessStartUs, WallMicros());
}

TEST(Signing, AKeyFileOthersCanReadIsRefused) {
  const std::string path = testing::TempDir() + "/ftc_bus_key";
  std::ofstream(path) << std::string(64, 'a') << "\n";
  Key key;
  chmod(path.c_str(), 0644);
  EXPECT_NE(LoadKey(path, &key).find("readable or writable by others"), std::string::npos);
  chmod(path.c_str(), 0600);
  EXPECT_EQ(LoadKey(path, &key), "");
  EXPECT_EQ(key, Key(32, 0xaa));
  std::ofstream(path) << "abcd\n";
  EXPECT_NE(LoadKey(path, &key).find("at least 32 hex digits"), std::string::npos);
  std::remove(path.c_str());
}

TEST(Signing, AKeyFileIsARegularFileOfAtMost4096Bytes) {
  // what a careless or hostile setup may give as --key-file: each a one-line
  // refusal naming the file (a directory threw out of main, exit 134; a FIFO
  // blocked the process for good; a device would be read without end)
  const std::string dir = testing::TempDir() + "/ftc_key_cases";
  mkdir(dir.c_str(), 0700);
  Key key;
  EXPECT_NE(LoadKey(dir, &key).find(dir + ": the key file is not a regular file"),
            std::string::npos);
  const std::string fifo = dir + "/fifo";
  std::remove(fifo.c_str());
  ASSERT_EQ(mkfifo(fifo.c_str(), 0600), 0);
  EXPECT_NE(LoadKey(fifo, &key).find("not a regular file"), std::string::npos);
  const std::string empty = dir + "/empty";
  std::ofstream(empty).close();
  chmod(empty.c_str(), 0600);
  EXPECT_NE(LoadKey(empty, &key).find("at least 32 hex digits"), std::string::npos);
  const std::string big = dir + "/big";
  std::ofstream(big) << std::string(5000, 'a');
  chmod(big.c_str(), 0600);
  EXPECT_NE(LoadKey(big, &key).find("5000 bytes"), std::string::npos);
  // a symbolic link is followed: its target's mode and contents count
  const std::string good = dir + "/good", link = dir + "/link";
  std::ofstream(good) << std::string(64, 'b') << "\n";
  chmod(good.c_str(), 0600);
  std::remove(link.c_str());
  ASSERT_EQ(symlink(good.c_str(), link.c_str()), 0);
  EXPECT_EQ(LoadKey(link, &key), "");
  EXPECT_EQ(key, Key(32, 0xbb));
  chmod(good.c_str(), 0640);
  EXPECT_NE(LoadKey(link, &key).find("readable or writable by others"), std::string::npos);
  EXPECT_NE(LoadKey(dir + "/none", &key).find("cannot read the key file"), std::string::npos);
  for (const auto& f : {fifo, empty, big, link, good}) std::remove(f.c_str());
  rmdir(dir.c_str());
}

}  // namespace
}  // namespace ftc::signing
