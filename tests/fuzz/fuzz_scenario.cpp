// libFuzzer target: scenario parsing (ftc::ParseScenario, what the plant,
// ftc.simulate and ftc.mpc run on a --scenario file). Properties:
//   * any text either parses or throws ScenarioError (the plant's exit 2);
//     any other exception escaping is a finding (the plant would exit 1);
//   * an accepted scenario is one the plant can run: factors > 0 and not NaN,
//     steps_per_interval > 0, finite noise >= 0, and the degraded parameters
//     finite at every age an experiment reaches;
//   * its events are sorted by at_step >= 0, with indices in range, factors as
//     above and stuck states 0/1, and the parameters finite at each event's step;
//   * the plant core constructs from it and takes a step without throwing, also
//     at the first event's step.
// Built only with -DFTC_FUZZ=ON (scripts/fuzz.sh).
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <string>

#include "plant/core/degradation.h"
#include "plant/core/plant.h"
#include "plant/core/scenario.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size > 4096) return 0;  // scenario files are a few lines
  const std::string text(reinterpret_cast<const char*>(data), size);
  ftc::FaultScenario s;
  try {
    s = ftc::ParseScenario(text, "fuzz.toml");
  } catch (const ftc::ScenarioError&) {
    return 0;
  }
  for (int i = 0; i < ftc::kTanks; ++i)
    if (std::isnan(s.tank_factor[i]) || !(s.tank_factor[i] > 0)) std::abort();
  for (int j = 0; j < ftc::kEngines; ++j)
    if (std::isnan(s.engine_factor[j]) || !(s.engine_factor[j] > 0)) std::abort();
  if (s.steps_per_interval <= 0 || !std::isfinite(s.noise_std) || s.noise_std < 0) std::abort();
  for (double age : {0.0, 0.5, 1.0, 10.0, 100.0}) {
    const ftc::PlantParams p = ftc::DegradedParams(ftc::PlantParams{}, s, age);
    if (!p.pump.allFinite() || !p.resistance.allFinite() || !p.demand.allFinite()) std::abort();
  }
  std::int64_t previous = 0;
  for (const ftc::FaultEvent& e : s.events) {
    if (e.at_step < previous) std::abort();
    previous = e.at_step;
    const int count = e.kind == ftc::FaultEvent::Kind::kEngine ? ftc::kEngines : ftc::kTanks;
    if (e.index < 0 || e.index >= count) std::abort();
    if (e.kind == ftc::FaultEvent::Kind::kStuckValve) {
      if (e.state != 0 && e.state != 1) std::abort();
    } else if (std::isnan(e.factor) || !(e.factor > 0)) {
      std::abort();
    }
    const ftc::PlantParams p = ftc::DegradedParamsAtStep(ftc::PlantParams{}, s, e.at_step);
    if (!p.pump.allFinite() || !p.resistance.allFinite() || !p.demand.allFinite()) std::abort();
  }
  ftc::Plant plant(s, 0);
  plant.Step(ftc::Valves::Ones());
  if (!s.events.empty()) {
    ftc::Plant late(s, 0);
    late.SetOperatingSteps(s.events.front().at_step);
    const ftc::StepOutcome& o = late.Step(ftc::Valves::Ones());
    const ftc::Valves applied =
        ftc::StuckValvesAtStep(s, s.events.front().at_step).Apply(ftc::Valves::Ones());
    if (o.valves != applied) std::abort();
  }
  return 0;
}
