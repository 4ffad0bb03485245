// lcm_recorder: records LCM traffic to a log file in lcm-logger's format
// (readable by lcm.EventLog, lcm-logplayer, ftc.replay), without losing
// lockstep traffic on a busy machine.
//
// Why not lcm-logger itself: LCM queues at most 30 undispatched messages per
// subscription by default, and lcm-logger keeps that default; a plant and
// controller in lockstep exchange thousands of messages a second, so a
// recorder descheduled for ~10 ms on a loaded 2-core machine dropped plant
// states (measured: 2 to 752 of ~5,000 per run). This recorder lifts the
// queue limit to kQueueCapacity messages (tens of seconds of lockstep traffic)
// and writes from the handler, so a stall is absorbed by the queue and the
// kernel's socket buffer (raised by scripts/setup.sh), while a flood from a
// neighbour cannot grow the queue without bound. It never decodes what it
// records (raw bytes in, raw bytes out), so no content can crash it.
#include <lcm/lcm-cpp.hpp>

#include <CLI/CLI.hpp>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <iostream>
#include <memory>
#include <string>

namespace {

volatile std::sig_atomic_t g_stop = 0;
// ~50 MB of plant states (250 bytes each); beyond it LCM drops, as its default 30 did
constexpr int kQueueCapacity = 200000;
void OnSignal(int) { g_stop = 1; }

struct EventLogDestroy {
  void operator()(lcm_eventlog_t* log) const { lcm_eventlog_destroy(log); }
};
using EventLogPtr = std::unique_ptr<lcm_eventlog_t, EventLogDestroy>;

class Recorder final {
 public:
  explicit Recorder(lcm_eventlog_t* log) : log_(log) {}
  Recorder(const Recorder&) = delete;
  Recorder& operator=(const Recorder&) = delete;

  void OnMessage(const lcm::ReceiveBuffer* rbuf, const std::string& channel) {
    lcm_eventlog_event_t event{};
    event.timestamp = rbuf->recv_utime;
    event.channellen = static_cast<int32_t>(channel.size());
    event.channel = const_cast<char*>(channel.c_str());
    event.datalen = static_cast<int32_t>(rbuf->data_size);
    event.data = rbuf->data;
    if (lcm_eventlog_write_event(log_, &event) != 0) {
      std::cerr << "lcm_recorder: error: write failed (disk full?)\n";
      failed_ = true;
      g_stop = 1;
    }
  }
  bool failed() const { return failed_; }

 private:
  lcm_eventlog_t* log_;
  bool failed_ = false;
};

}  // namespace

// Exit codes as ftc.common.errors: 1 LCM failed, 2 bad options or the file
// cannot be opened, 5 a write to the file failed (disk full).
constexpr int kExitStorage = 5;

int main(int argc, char** argv) {
  std::string url = "udpm://239.255.76.67:7667?ttl=0";
  std::string channel = ".*";
  std::string path;
  int flush_ms = 100;
  CLI::App app{
      "Record LCM traffic to a log file (lcm-logger's format) with no per-subscription "
      "queue limit, so lockstep traffic is not dropped when the recorder is briefly "
      "descheduled. Stops cleanly on SIGINT/SIGTERM."};
  app.add_option("--lcm-url", url, "LCM provider URL")->capture_default_str();
  app.add_option("-c,--channel", channel, "Channel regex to record")->capture_default_str();
  app.add_option("--flush-interval", flush_ms, "Flush the file every MS milliseconds")
      ->check(CLI::PositiveNumber)
      ->capture_default_str();
  app.add_option("file", path, "Log file to write (overwritten)")->required();
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e) == 0 ? 0 : 2;
  }
  // Declared before the LCM instance: closed (flushed) after LCM stops delivering.
  const EventLogPtr log(lcm_eventlog_create(path.c_str(), "w"));
  if (!log) {
    std::cerr << "lcm_recorder: error: cannot open '" << path << "' for writing\n";
    return 2;
  }
  int rc = 0;
  {
    lcm::LCM lcm(url);
    if (!lcm.good()) {
      std::cerr << "lcm_recorder: error: cannot open LCM at '" << url << "'\n";
      return 1;
    }
    // liblcm opens the receive socket on first use and, when that fails (the
    // port taken by a socket that does not share it), leaves subscriptions
    // that crash: open it now and say so instead
    if (lcm.getFileno() < 0) {
      std::cerr << "lcm_recorder: error: cannot receive on '" << url
                << "' (its port is taken by another socket)\n";
      return 1;
    }
    Recorder recorder(log.get());
    lcm::Subscription* sub = lcm.subscribe(channel, &Recorder::OnMessage, &recorder);
    sub->setQueueCapacity(kQueueCapacity);  // see the file comment
    std::signal(SIGINT, OnSignal);
    std::signal(SIGTERM, OnSignal);
    using Clock = std::chrono::steady_clock;
    auto next_flush = Clock::now() + std::chrono::milliseconds(flush_ms);
    while (!g_stop) {
      if (lcm.handleTimeout(flush_ms) < 0 && !g_stop) {
        std::cerr << "lcm_recorder: error: LCM receive failed\n";
        rc = 1;
        break;
      }
      if (Clock::now() >= next_flush) {
        if (std::fflush(log->f) != 0) {  // buffered writes fail here (disk full)
          std::cerr << "lcm_recorder: error: write to '" << path << "' failed (disk full?)\n";
          rc = kExitStorage;
          break;
        }
        next_flush = Clock::now() + std::chrono::milliseconds(flush_ms);
      }
    }
    // Drain what already arrived before closing.
    while (!recorder.failed() && lcm.handleTimeout(0) > 0) {
    }
    if (recorder.failed()) rc = kExitStorage;
    if (rc == 0 && std::fflush(log->f) != 0) {
      std::cerr << "lcm_recorder: error: write to '" << path << "' failed (disk full?)\n";
      rc = kExitStorage;
    }
  }
  return rc;
}
