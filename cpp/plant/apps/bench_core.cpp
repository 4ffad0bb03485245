// Benchmark of the in-process CVODE step: median wall time of one 1 s control
// step, with valves held (no switches beyond pump events) and with the valves
// changed every step (a re-initialisation per step), on the multiple-fault
// parameters at age 5. Prints one line per case; used by scripts/bench_plant.py.
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <random>
#include <vector>

#include "plant/core/degradation.h"
#include "plant/core/integrator.h"

namespace {

double MedianMicros(std::vector<double> v) {
  std::nth_element(v.begin(), v.begin() + v.size() / 2, v.end());
  return v[v.size() / 2];
}

}  // namespace

int main(int argc, char** argv) {
  const int steps = argc > 1 ? std::atoi(argv[1]) : 20000;
  ftc::FaultScenario s;
  s.engine_factor[0] = 20.0;
  s.tank_factor[4] = s.tank_factor[5] = 20.0;
  const ftc::PlantParams p = ftc::DegradedParams(ftc::PlantParams{}, s, 5.0);
  ftc::StepIntegrator integrator;
  std::mt19937_64 rng(1);
  using Clock = std::chrono::steady_clock;

  for (const bool change : {false, true}) {
    std::vector<double> times;
    times.reserve(steps);
    ftc::Vec6 x = ftc::Vec6::Ones();
    ftc::Valves u = ftc::Valves::Zero();
    u << 1, 0, 1, 0, 1, 0;
    int events = 0;
    for (int k = 0; k < steps; ++k) {
      if (change)
        for (int i = 0; i < ftc::kTanks; ++i) u[i] = static_cast<int>(rng() & 1);
      const auto t0 = Clock::now();
      const auto r = integrator.Step(x, u, p, 1.0);
      times.push_back(std::chrono::duration<double, std::micro>(Clock::now() - t0).count());
      x = r.x;
      events += r.events;
      if (x.sum() < 0.3) x = ftc::Vec6::Ones();  // new episode
    }
    std::printf("%s median_us=%.3f events_per_step=%.2f steps=%d\n",
                change ? "valves_changing" : "valves_held", MedianMicros(times),
                static_cast<double>(events) / steps, steps);
  }
  return 0;
}
