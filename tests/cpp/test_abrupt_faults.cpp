// Abrupt faults ([[event]] tables of a scenario): parsing, the parameter jump
// at at_step against the degradation formulas, stuck valves applied by the
// plant (and fuel still conserved), and evaluation episodes frozen at the last
// operating step's parameters and stuck valves.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <string>

#include "plant/core/degradation.h"
#include "plant/core/plant.h"
#include "plant/core/scenario.h"

namespace ftc {
namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kExact = 1e-12;  // closed-form products of a few doubles
constexpr double kLevel = 1e-7;   // integrated levels over one step (CVODE tolerances)

Valves V(int a, int b, int c, int d, int e, int f) {
  Valves u;
  u << a, b, c, d, e, f;
  return u;
}

// ---------------------------------------------------------------------------
// Parsing

TEST(AbruptFaults, EventsParseAndSortByStep) {
  const FaultScenario s = ParseScenario(R"(
engine_factor = [20.0, inf]
[[event]]
at_step = 3100
stuck_valve = 2
state = "open"
[[event]]
at_step = 2600
tank = 4
factor = 2       # an integer is a number
[[event]]
at_step = 3000
engine = 1
factor = 3.0
[[event]]
at_step = 3000
stuck_valve = 6
state = "closed"
[[event]]
at_step = 0
tank = 1
factor = inf     # healthy again: a repair
)", "inline.toml");
  ASSERT_EQ(s.events.size(), 5u);
  EXPECT_EQ(s.events[0].at_step, 0);
  EXPECT_EQ(s.events[0].kind, FaultEvent::Kind::kTank);
  EXPECT_EQ(s.events[0].index, 0);
  EXPECT_TRUE(std::isinf(s.events[0].factor));
  EXPECT_EQ(s.events[1].at_step, 2600);
  EXPECT_EQ(s.events[1].index, 3);  // tank 4, 1-based in the file
  EXPECT_EQ(s.events[1].factor, 2.0);
  // Two events at step 3000 keep the file's order (stable sort).
  EXPECT_EQ(s.events[2].kind, FaultEvent::Kind::kEngine);
  EXPECT_EQ(s.events[2].index, 0);
  EXPECT_EQ(s.events[2].factor, 3.0);
  EXPECT_EQ(s.events[3].kind, FaultEvent::Kind::kStuckValve);
  EXPECT_EQ(s.events[3].index, 5);
  EXPECT_EQ(s.events[3].state, 0);
  EXPECT_EQ(s.events[4].at_step, 3100);
  EXPECT_EQ(s.events[4].index, 1);
  EXPECT_EQ(s.events[4].state, 1);
  // The linear factors are not touched by the events.
  EXPECT_EQ(s.engine_factor[0], 20.0);
  EXPECT_TRUE(std::isinf(s.tank_factor[3]));
}

TEST(AbruptFaults, ShippedExampleLoadsAndOlderScenariosHaveNoEvents) {
  const std::string dir = std::string(FTC_SOURCE_DIR) + "/scenarios/";
  for (const char* name : {"nominal.toml", "single.toml", "multiple.toml"})
    EXPECT_TRUE(LoadScenario(dir + name).events.empty()) << name;
  const FaultScenario abrupt = LoadScenario(dir + "abrupt.toml");
  EXPECT_EQ(abrupt.events.size(), 2u);
  EXPECT_EQ(abrupt.engine_factor[0], 20.0);
}

struct BadEvent {
  const char* text;    // TOML appended after a valid first line
  const char* key;     // the key the message must name
  const char* detail;  // a fragment the message must contain
};

class AbruptFaultErrors : public ::testing::TestWithParam<BadEvent> {};

TEST_P(AbruptFaultErrors, NameTheFileAndTheKey) {
  const BadEvent c = GetParam();
  const std::string text = std::string("engine_factor = [20.0, inf]\n") + c.text;
  try {
    ParseScenario(text, "events.toml");
    FAIL() << "accepted:\n" << text;
  } catch (const ScenarioError& e) {
    const std::string msg = e.what();
    EXPECT_EQ(msg.rfind("events.toml: ", 0), 0u) << msg;
    EXPECT_NE(msg.find(std::string("key '") + c.key + "'"), std::string::npos) << msg;
    EXPECT_NE(msg.find(c.detail), std::string::npos) << msg;
  }
}

constexpr const char* kOk = "[[event]]\nat_step = 1\ntank = 1\nfactor = 5.0\n";

INSTANTIATE_TEST_SUITE_P(
    Malformed, AbruptFaultErrors,
    ::testing::Values(
        BadEvent{"[[event]]\nat_step = -1\ntank = 1\nfactor = 5.0\n", "event[1].at_step",
                 "integer >= 0"},
        BadEvent{"[[event]]\nat_step = 2600.0\ntank = 1\nfactor = 5.0\n", "event[1].at_step",
                 "expected an integer, got float"},
        BadEvent{"[[event]]\nat_step = \"2600\"\ntank = 1\nfactor = 5.0\n", "event[1].at_step",
                 "got string"},
        BadEvent{"[[event]]\ntank = 1\nfactor = 5.0\n", "event[1].at_step", "missing"},
        BadEvent{"[[event]]\nat_step = 5\nfactor = 5.0\n", "event[1]",
                 "needs one of tank, engine, stuck_valve"},
        BadEvent{"[[event]]\nat_step = 5\ntank = 1\nengine = 1\nfactor = 5.0\n", "event[1]",
                 "gives both engine and tank; an event changes exactly one of tank, engine, "
                 "stuck_valve"},
        BadEvent{"[[event]]\nat_step = 5\ntank = 2\nstuck_valve = 2\nstate = \"open\"\n",
                 "event[1]", "exactly one of"},
        BadEvent{"[[event]]\nat_step = 5\ntank = 0\nfactor = 5.0\n", "event[1].tank",
                 "must be 1..6 (1-based), got 0"},
        BadEvent{"[[event]]\nat_step = 5\ntank = 7\nfactor = 5.0\n", "event[1].tank",
                 "must be 1..6"},
        BadEvent{"[[event]]\nat_step = 5\ntank = 4.0\nfactor = 5.0\n", "event[1].tank",
                 "expected an integer, got float"},
        BadEvent{"[[event]]\nat_step = 5\nengine = 3\nfactor = 5.0\n", "event[1].engine",
                 "must be 1..2"},
        BadEvent{"[[event]]\nat_step = 5\nstuck_valve = 7\nstate = \"open\"\n",
                 "event[1].stuck_valve", "must be 1..6"},
        BadEvent{"[[event]]\nat_step = 5\ntank = 1\nfactor = 1e-4\n", "event[1].factor",
                 "at least 0.001"},
        BadEvent{"[[event]]\nat_step = 5\ntank = 1\nfactor = 0.0\n", "event[1].factor",
                 "must be > 0"},
        BadEvent{"[[event]]\nat_step = 5\nengine = 1\nfactor = nan\n", "event[1].factor",
                 "must be > 0"},
        BadEvent{"[[event]]\nat_step = 5\nengine = 1\nfactor = -inf\n", "event[1].factor",
                 "must be > 0"},
        BadEvent{"[[event]]\nat_step = 5\nengine = 1\nfactor = \"2\"\n", "event[1].factor",
                 "expected a number, got string"},
        BadEvent{"[[event]]\nat_step = 5\nengine = 1\n", "event[1].factor", "missing"},
        BadEvent{"[[event]]\nat_step = 5\nengine = 1\nfactor = 2.0\nstate = \"open\"\n",
                 "event[1].state", "only for stuck_valve"},
        BadEvent{"[[event]]\nat_step = 5\nstuck_valve = 1\n", "event[1].state", "missing"},
        BadEvent{"[[event]]\nat_step = 5\nstuck_valve = 1\nstate = \"half\"\n", "event[1].state",
                 "expected \"open\" or \"closed\", got \"half\""},
        BadEvent{"[[event]]\nat_step = 5\nstuck_valve = 1\nstate = true\n", "event[1].state",
                 "expected a string, got boolean"},
        BadEvent{"[[event]]\nat_step = 5\nstuck_valve = 1\nstate = \"open\"\nfactor = 2.0\n",
                 "event[1].factor", "not allowed for stuck_valve"},
        BadEvent{"[[event]]\nat_step = 5\ntank = 1\nfactor = 2.0\nwhen = 3\n", "event[1].when",
                 "unknown key"},
        // The second event is the bad one: the message counts from 1.
        BadEvent{"[[event]]\nat_step = 1\ntank = 1\nfactor = 5.0\n"
                 "[[event]]\nat_step = 5\ntank = 9\nfactor = 5.0\n",
                 "event[2].tank", "must be 1..6"},
        BadEvent{"[event]\nat_step = 5\ntank = 1\nfactor = 2.0\n", "event",
                 "expected [[event]] tables, got table"},
        BadEvent{"event = 3\n", "event", "expected [[event]] tables, got integer"},
        BadEvent{"event = [1, 2]\n", "event", "expected [[event]] tables, got array"},
        BadEvent{"[[events]]\nat_step = 5\ntank = 1\nfactor = 2.0\n", "events",
                 "unknown key (known: name, tank_factor"}));

TEST(AbruptFaults, TheBadCasesDifferFromAGoodOneOnlyInTheirEvents) {
  const std::string text = std::string("engine_factor = [20.0, inf]\n") + kOk;
  EXPECT_EQ(ParseScenario(text, "events.toml").events.size(), 1u);
}

// ---------------------------------------------------------------------------
// The parameter jump

FaultScenario JumpScenario() {
  // E1 wears linearly (D = 20); from operating step 1030 (age 2, interval 2)
  // tank 4 gets D_T = 2.5 and engine 1 D_E = 5.
  FaultScenario s = ParseScenario(R"(
engine_factor = [20.0, inf]
[[event]]
at_step = 1030
tank = 4
factor = 2.5
[[event]]
at_step = 1030
engine = 1
factor = 5.0
)", "jump.toml");
  return s;
}

TEST(AbruptFaults, ParametersJumpAtTheEventStepWithTheSameAge) {
  const FaultScenario s = JumpScenario();
  const PlantParams n;
  const PlantParams before = DegradedParamsAtStep(n, s, 1029);
  const PlantParams after = DegradedParamsAtStep(n, s, 1030);
  const PlantParams later = DegradedParamsAtStep(n, s, 2600);  // age 5
  // Before: tank 4 healthy, d_1 = d0 (1 + 2/20).
  EXPECT_EQ(before.pump[3], 0.1);
  EXPECT_EQ(before.resistance[3], 100.0);
  EXPECT_NEAR(before.demand[0], 0.05 * (1 + 2.0 / 20), kExact);
  // From at_step on, the new D at the same age a = 2.
  EXPECT_NEAR(after.pump[3], 0.1 * (1 - 2.0 / 2.5), kExact);
  EXPECT_NEAR(after.resistance[3], 100.0 * (1 + 2.0 / 2.5), kExact);
  EXPECT_NEAR(after.demand[0], 0.05 * (1 + 2.0 / 5.0), kExact);
  // And it keeps wearing with the new D: at age 5 the pump is dead (max(0, .)).
  EXPECT_EQ(later.pump[3], 0.0);
  EXPECT_NEAR(later.resistance[3], 100.0 * (1 + 5.0 / 2.5), kExact);
  EXPECT_NEAR(later.demand[0], 0.05 * (1 + 5.0 / 5.0), kExact);
  // Untouched components: as without events.
  for (int i : {0, 1, 2, 4, 5}) EXPECT_EQ(after.pump[i], 0.1);
  EXPECT_EQ(after.demand[1], 0.05);
  // Without events: bit-identical to DegradedParams at AgeAt.
  FaultScenario plain = s;
  plain.events.clear();
  for (std::int64_t k : {0, 511, 512, 1030, 5000}) {
    const PlantParams a = DegradedParamsAtStep(n, plain, k);
    const PlantParams b = DegradedParams(n, plain, AgeAt(plain, k));
    EXPECT_EQ(a.pump, b.pump);
    EXPECT_EQ(a.resistance, b.resistance);
    EXPECT_EQ(a.demand, b.demand);
  }
  // Continuous mode: the age is the fraction, the jump as sharp.
  FaultScenario c = s;
  c.mode = DegradationMode::kContinuous;
  EXPECT_EQ(DegradedParamsAtStep(n, c, 1029).pump[3], 0.1);
  EXPECT_NEAR(DegradedParamsAtStep(n, c, 1030).pump[3], 0.1 * (1 - (1030.0 / 512) / 2.5),
              kExact);
}

TEST(AbruptFaults, LaterEventsOnAComponentReplaceEarlierOnes) {
  const FaultScenario s = ParseScenario(R"(
[[event]]
at_step = 10
engine = 2
factor = 4.0
[[event]]
at_step = 20
engine = 2
factor = inf
[[event]]
at_step = 20
engine = 2
factor = 8.0
)", "replace.toml");
  EXPECT_TRUE(std::isinf(FactorsAtStep(s, 9).engine_factor[1]));
  EXPECT_EQ(FactorsAtStep(s, 10).engine_factor[1], 4.0);
  EXPECT_EQ(FactorsAtStep(s, 19).engine_factor[1], 4.0);
  EXPECT_EQ(FactorsAtStep(s, 20).engine_factor[1], 8.0);  // the file's last at step 20
}

TEST(AbruptFaults, ThePlantStepsWithTheJumpedParameters) {
  // Full tanks, valves closed: each engine draws its demand from its innermost
  // tank while that tank's pump can give it, the rest from the next tank out.
  Plant plant(JumpScenario(), 0);
  plant.SetOperatingSteps(1029);
  plant.Reset();
  const StepOutcome a = plant.Step(Valves::Zero());  // operating step 1029
  EXPECT_EQ(a.age, 2.0);
  EXPECT_NEAR(1.0 - a.level[2], 0.05 * 1.1, kLevel);  // d_1 with D_E = 20
  EXPECT_NEAR(1.0 - a.level[3], 0.05, kLevel);        // tank 4's healthy pump
  EXPECT_NEAR(1.0 - a.level[4], 0.0, kLevel);
  const Vec6 x = a.level;
  const StepOutcome b = plant.Step(Valves::Zero());  // operating step 1030: the event
  EXPECT_EQ(b.age, 2.0);
  EXPECT_NEAR(x[2] - b.level[2], 0.05 * (1 + 2.0 / 5.0), kLevel);
  EXPECT_NEAR(x[3] - b.level[3], 0.1 * (1 - 2.0 / 2.5), kLevel);          // p_4 = 0.02
  EXPECT_NEAR(x[4] - b.level[4], 0.05 - 0.1 * (1 - 2.0 / 2.5), kLevel);   // the rest
  EXPECT_EQ(plant.operating_steps(), 1031);
}

// ---------------------------------------------------------------------------
// Stuck valves

FaultScenario StuckScenario() {
  return ParseScenario(R"(
[[event]]
at_step = 3
stuck_valve = 1
state = "open"
[[event]]
at_step = 3
stuck_valve = 6
state = "closed"
)", "stuck.toml");
}

TEST(AbruptFaults, StuckValvesFromTheirStep) {
  const FaultScenario s = StuckScenario();
  EXPECT_FALSE(StuckValvesAtStep(s, 2).any());
  const StuckValves v = StuckValvesAtStep(s, 3);
  EXPECT_EQ(v.mask, V(1, 0, 0, 0, 0, 1));
  EXPECT_EQ(v.state, V(1, 0, 0, 0, 0, 0));
  EXPECT_EQ(v.Apply(V(0, 1, 0, 1, 0, 1)), V(1, 1, 0, 1, 0, 0));
  EXPECT_EQ(v.Apply(V(1, 0, 1, 0, 1, 0)), V(1, 0, 1, 0, 1, 0));
}

TEST(AbruptFaults, ThePlantAppliesStuckValvesAndConservesFuel) {
  Plant stuck(StuckScenario(), 0);
  Plant healthy(FaultScenario{}, 0);
  stuck.Reset();
  healthy.Reset();
  const Valves command = V(0, 0, 1, 1, 0, 1);  // valve 1 not asked, valve 6 asked open
  for (int k = 0; k < 40; ++k) {
    const Vec6 x0 = stuck.last().level;
    const StepOutcome& o = stuck.Step(command);
    // What the plant applied is published; before step 3 the command itself.
    const Valves applied = k < 3 ? command : V(1, 0, 1, 1, 0, 0);
    EXPECT_EQ(o.valves, applied) << "step " << k;
    const StepOutcome& h = healthy.Step(applied);
    EXPECT_EQ(o.level, h.level) << "step " << k;  // the same physics, bit for bit
    // Conservation: the total falls by exactly what the pumps supplied.
    const double supplied = 0.1 - o.deficit.sum();
    EXPECT_NEAR(x0.sum() - o.level.sum(), supplied, kLevel) << "step " << k;
    EXPECT_GE(o.level.minCoeff(), 0.0);
    EXPECT_LE(o.level.maxCoeff(), 1.0);
  }
  // Valve 1 stuck open did move fuel: tank 1 fed tank 3 (E1 drains tank 3).
  EXPECT_LT(stuck.last().level[0], 1.0 - 1e-3);
  EXPECT_EQ(stuck.operating_steps(), 40);
}

// ---------------------------------------------------------------------------
// Evaluation episodes

TEST(AbruptFaults, EvaluationIsFrozenAtTheLastOperatingStep) {
  // At step 10 E1's demand doubles at once (D_E = 1, continuous age 10/100 ->
  // d = 0.05 (1 + 0.1)) and valve 1 sticks open; nothing before.
  FaultScenario s = ParseScenario(R"(
degradation = "continuous"
steps_per_interval = 100
[[event]]
at_step = 10
engine = 1
factor = 1.0
[[event]]
at_step = 10
stuck_valve = 1
state = "open"
)", "eval.toml");
  Plant plant(s, 0);
  plant.Reset();
  for (int k = 0; k < 10; ++k) plant.Step(Valves::Zero());  // steps 0..9: no event yet
  EXPECT_EQ(plant.operating_steps(), 10);
  plant.ResetEvaluation();
  EXPECT_EQ(plant.step_in_force(), 9);
  EXPECT_NEAR(plant.current_age(), 0.09, kExact);
  for (int k = 0; k < 70; ++k) {  // past its end: a new evaluation episode, same freeze
    const Vec6 x0 = plant.episode_over() ? Vec6::Ones() : plant.last().level;
    const StepOutcome& o = plant.Step(Valves::Zero());
    ASSERT_TRUE(o.evaluation);
    EXPECT_EQ(o.valves, Valves::Zero());  // not stuck yet at step 9
    EXPECT_NEAR(o.age, 0.09, kExact);
    if (o.step == 1) EXPECT_NEAR(x0[2] - o.level[2], 0.05, kLevel);  // E1 still healthy
  }
  EXPECT_EQ(plant.operating_steps(), 10);  // evaluation steps do not count

  plant.Reset();
  const StepOutcome& o10 = plant.Step(Valves::Zero());  // operating step 10: the event
  EXPECT_EQ(o10.valves, V(1, 0, 0, 0, 0, 0));
  EXPECT_NEAR(1.0 - o10.level[2], 0.05 * (1 + 0.1 / 1.0), kLevel);
  plant.ResetEvaluation();
  EXPECT_EQ(plant.step_in_force(), 10);
  const StepOutcome& e = plant.Step(Valves::Zero());
  EXPECT_TRUE(e.evaluation);
  EXPECT_EQ(e.valves, V(1, 0, 0, 0, 0, 0));  // stuck in evaluation too
  EXPECT_NEAR(1.0 - e.level[2], 0.05 * (1 + 0.1 / 1.0), kLevel);
  EXPECT_NEAR(e.age, 0.1, kExact);
  EXPECT_EQ(plant.operating_steps(), 11);
  // Before any operating step an evaluation uses step 0's parameters.
  Plant fresh(s, 0);
  fresh.ResetEvaluation();
  EXPECT_EQ(fresh.step_in_force(), 0);
}

}  // namespace
}  // namespace ftc
