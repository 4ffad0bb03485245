// Message authentication on the bus, MAVLink 2's signing idea done with a
// real MAC. With a shared key configured, every message carries a trailer
// after its LCM encoding:
//
//   payload | link id (1 byte) | timestamp (6 bytes, big-endian, 10 us units
//   since the Unix epoch) | HMAC-SHA256(key, channel | 0x00 | payload | link id
//   | timestamp), its first kMacBytes bytes
//
// A receiver refuses (and counts, by cause) a message whose MAC does not
// verify or that carries none (bad signature), whose timestamp is not above
// the last one it accepted from that link (replay), or older than its window
// (stale). A receiver's links start at its own start time: a message signed
// before the receiving process started (recorded off the bus and replayed to a
// restarted plant or node with the same key file, within the window) counts
// as a replay too. Python's side: python/ftc/plant/signing.py (the same bytes).
//
// Header-only over OpenSSL's libcrypto (the policy node includes it too). The
// MAC's context is keyed once per signer and verifier and re-initialised with
// that key for each message (OpenSSL's EVP_MAC; the one-shot HMAC() fetches
// the digest and sets the key up on every call: measured 5.9 us a message
// against 1.4 us on this machine, see scripts/bench_realtime.py).
#pragma once

#include <openssl/core_names.h>
#include <openssl/crypto.h>
#include <openssl/evp.h>
#include <openssl/hmac.h>
#include <openssl/params.h>
#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cctype>
#include <cerrno>
#include <chrono>
#include <cstdint>
#include <cstring>
#include <fstream>
#include <initializer_list>
#include <iterator>
#include <memory>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

namespace ftc::signing {

constexpr std::size_t kMacBytes = 16;  // 128 of HMAC-SHA256's 256 bits
constexpr std::size_t kTrailerBytes = 1 + 6 + kMacBytes;
constexpr std::int64_t kTickUs = 10;                   // the timestamp's unit
constexpr std::size_t kMinKeyBytes = 16;
constexpr std::int64_t kDefaultWindowUs = 30'000'000;  // older than this: stale

using Key = std::vector<unsigned char>;
using Digest = std::array<unsigned char, 32>;

inline std::int64_t WallMicros() {
  return std::chrono::duration_cast<std::chrono::microseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}
// The wall clock when this process started (set before main runs, so before
// any receive socket opens): the default floor of a Verifier's timestamps.
inline const std::int64_t kProcessStartUs = WallMicros();

inline Digest HmacSha256(const Key& key, const unsigned char* data, std::size_t n) {
  Digest out{};
  unsigned int len = 0;
  HMAC(EVP_sha256(), key.data(), static_cast<int>(key.size()), data, n, out.data(), &len);
  return out;
}

// HMAC-SHA256 under one key, its context set up once: Of() MACs the
// concatenation of the pieces given (no copy of them). std::runtime_error if
// OpenSSL cannot set it up.
class Hmac final {
 public:
  struct Piece {
    const unsigned char* data;
    std::size_t size;
  };

  explicit Hmac(const Key& key) {
    std::unique_ptr<EVP_MAC, decltype(&EVP_MAC_free)> mac(EVP_MAC_fetch(nullptr, "HMAC", nullptr),
                                                          &EVP_MAC_free);
    if (mac) ctx_.reset(EVP_MAC_CTX_new(mac.get()));
    char digest[] = "SHA256";
    const OSSL_PARAM params[] = {
        OSSL_PARAM_construct_utf8_string(OSSL_MAC_PARAM_DIGEST, digest, 0), OSSL_PARAM_END};
    if (!ctx_ || EVP_MAC_init(ctx_.get(), key.data(), key.size(), params) != 1)
      throw std::runtime_error("OpenSSL: cannot set up HMAC-SHA256");
  }

  Digest Of(std::initializer_list<Piece> pieces) {
    Digest out{};
    std::size_t len = 0;
    EVP_MAC_init(ctx_.get(), nullptr, 0, nullptr);  // the key given at construction
    for (const Piece& p : pieces) EVP_MAC_update(ctx_.get(), p.data, p.size);
    EVP_MAC_final(ctx_.get(), out.data(), &len, out.size());
    return out;
  }

 private:
  std::unique_ptr<EVP_MAC_CTX, decltype(&EVP_MAC_CTX_free)> ctx_{nullptr, &EVP_MAC_CTX_free};
};

// A key from hex text (whitespace around it ignored); "" or the reason.
inline std::string KeyFromHex(const std::string& text, Key* key) {
  std::string hex;
  for (char c : text)
    if (!std::isspace(static_cast<unsigned char>(c))) hex += c;
  if (hex.size() % 2 != 0 || hex.size() < 2 * kMinKeyBytes)
    return "a key is at least " + std::to_string(2 * kMinKeyBytes) +
           " hex digits (an even number)";
  key->clear();
  for (std::size_t i = 0; i < hex.size(); i += 2) {
    const std::string byte = hex.substr(i, 2);
    if (!std::isxdigit(static_cast<unsigned char>(byte[0])) ||
        !std::isxdigit(static_cast<unsigned char>(byte[1])))
      return "not hex: '" + byte + "'";
    key->push_back(static_cast<unsigned char>(std::stoi(byte, nullptr, 16)));
  }
  return {};
}

// The longest key file read (a 256-bit key is 64 hex digits and a newline).
constexpr long kMaxKeyFileBytes = 4096;

// The key in `path` (hex text). Refuses a file that others can read or
// write, and anything but a regular file of at most kMaxKeyFileBytes (a
// directory, a FIFO that would block, a device that never ends): "" or the
// reason naming the file. Opened without blocking and checked on the open
// descriptor, so the file checked is the file read.
inline std::string LoadKey(const std::string& path, Key* key) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_NONBLOCK | O_CLOEXEC);
  if (fd < 0) return path + ": cannot read the key file (" + std::strerror(errno) + ")";
  struct stat st {};
  std::string why;
  if (::fstat(fd, &st) != 0)
    why = path + ": cannot read the key file (" + std::strerror(errno) + ")";
  else if (!S_ISREG(st.st_mode))
    why = path + ": the key file is not a regular file";
  else if (st.st_mode & (S_IRWXG | S_IRWXO))
    why = path + ": the key file is readable or writable by others (chmod 600 it)";
  else if (st.st_size > kMaxKeyFileBytes)
    why = path + ": the key file has " + std::to_string(st.st_size) + " bytes (a key file has " +
          "at most " + std::to_string(kMaxKeyFileBytes) + ")";
  std::string text;
  if (why.empty()) {
    char buf[kMaxKeyFileBytes + 1];
    ssize_t n = 0;
    while ((n = ::read(fd, buf, sizeof buf)) > 0 &&
           text.size() <= static_cast<std::size_t>(kMaxKeyFileBytes))
      text.append(buf, static_cast<std::size_t>(n));
    if (n < 0) why = path + ": cannot read the key file (" + std::strerror(errno) + ")";
  }
  ::close(fd);
  if (!why.empty()) return why;
  why = KeyFromHex(text, key);
  return why.empty() ? why : path + ": " + why;
}

// The MAC of one message: over channel | 0x00 | payload | link id and timestamp (7 bytes).
inline Digest MessageMac(Hmac& hmac, const std::string& channel, const unsigned char* payload,
                         std::size_t n, const unsigned char* link_and_time) {
  static const unsigned char kZero = 0;
  return hmac.Of({{reinterpret_cast<const unsigned char*>(channel.data()), channel.size()},
                  {&kZero, 1},
                  {payload, n},
                  {link_and_time, 7}});
}

// Signs every message one sender publishes: timestamps rise strictly.
class Signer final {
 public:
  Signer(const Key& key, std::uint8_t link_id) : hmac_(key), link_id_(link_id) {}

  std::vector<unsigned char> Sign(const std::string& channel, const void* payload, std::size_t n,
                                  std::int64_t now_us) {
    std::int64_t ts = now_us / kTickUs;
    if (ts <= last_) ts = last_ + 1;
    last_ = ts;
    const auto* p = static_cast<const unsigned char*>(payload);
    std::vector<unsigned char> out(p, p + n);
    out.push_back(link_id_);
    for (int i = 5; i >= 0; --i) out.push_back(static_cast<unsigned char>(ts >> (8 * i)));
    const auto mac = MessageMac(hmac_, channel, p, n, out.data() + n);
    out.insert(out.end(), mac.begin(), mac.begin() + kMacBytes);
    return out;
  }

 private:
  Hmac hmac_;
  std::uint8_t link_id_;
  std::int64_t last_ = 0;
};

enum class Verdict { kOk, kBadSignature, kReplay, kStale };

inline const char* Describe(Verdict v) {
  switch (v) {
    case Verdict::kOk: return "ok";
    case Verdict::kBadSignature: return "bad or missing signature";
    case Verdict::kReplay: return "replayed (timestamp not above the link's last)";
    case Verdict::kStale: return "stale (timestamp older than the window)";
  }
  return "?";
}

// Checks the trailer of every message one receiver takes. Every link starts
// as if its last timestamp were just before `not_before_us` (default: when
// this process started), so what was signed before then is a replay.
class Verifier final {
 public:
  explicit Verifier(const Key& key, std::int64_t window_us = kDefaultWindowUs,
                    std::int64_t not_before_us = kProcessStartUs)
      : hmac_(key), window_ticks_(window_us / kTickUs) {
    last_.fill(std::max<std::int64_t>(0, not_before_us / kTickUs - 1));
  }

  // kOk with the payload's size (the bytes before the trailer) in *payload_size.
  Verdict Verify(const std::string& channel, const void* data, std::size_t size,
                 std::int64_t now_us, std::size_t* payload_size) {
    if (size < kTrailerBytes) return Verdict::kBadSignature;
    const auto* p = static_cast<const unsigned char*>(data);
    const std::size_t n = size - kTrailerBytes;
    const auto mac = MessageMac(hmac_, channel, p, n, p + n);
    if (CRYPTO_memcmp(mac.data(), p + n + 7, kMacBytes) != 0) return Verdict::kBadSignature;
    std::int64_t ts = 0;
    for (int i = 0; i < 6; ++i) ts = (ts << 8) | p[n + 1 + static_cast<std::size_t>(i)];
    std::int64_t& last = last_[p[n]];
    if (ts <= last) return Verdict::kReplay;
    if (ts < now_us / kTickUs - window_ticks_) return Verdict::kStale;
    last = ts;
    *payload_size = n;
    return Verdict::kOk;
  }

 private:
  Hmac hmac_;
  std::int64_t window_ticks_;
  std::array<std::int64_t, 256> last_{};  // per link id: the newest timestamp accepted
                                          // (at first: the floor)
};

}  // namespace ftc::signing
