// Python bindings of the physics core (imported as ftc._core): the same Plant
// the LCM process runs, for in-process rollouts, plus the pieces (degraded
// parameters, one integrated step, flows, reward) that the Python tests check
// against an independent reference. Arrays cross as numpy float64 / int arrays.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <algorithm>
#include <cctype>
#include <cstdint>
#include <cmath>
#include <limits>
#include <sstream>
#include <string>
#include <vector>

#include "plant/core/degradation.h"
#include "plant/core/dynamics.h"
#include "plant/core/integrator.h"
#include "plant/core/plant.h"
#include "plant/core/pool.h"
#include "plant/core/reward.h"
#include "plant/core/rollout.h"
#include "plant/core/scenario.h"

namespace py = pybind11;

void BindPool(py::module_& m);  // pool_bindings.cpp

namespace {

using ftc::kEngines;
using ftc::kTanks;

template <typename Derived>
py::array_t<typename Derived::Scalar> ToNumpy(const Eigen::MatrixBase<Derived>& v) {
  py::array_t<typename Derived::Scalar> a(v.size());
  auto out = a.template mutable_unchecked<1>();
  for (Eigen::Index k = 0; k < v.size(); ++k) out(k) = v[k];
  return a;
}

template <int N>
Eigen::Matrix<double, N, 1> ToVec(const py::handle& obj, const char* what) {
  const auto a = py::array_t<double, py::array::c_style | py::array::forcecast>::ensure(obj);
  if (!a || a.ndim() != 1 || a.shape(0) != N) {
    throw py::value_error(std::string(what) + " must be a sequence of " + std::to_string(N) +
                          " numbers");
  }
  Eigen::Matrix<double, N, 1> v;
  for (int k = 0; k < N; ++k) v[k] = a.at(k);
  return v;
}

ftc::Valves ToValves(const py::handle& obj) {
  const auto a = py::array_t<long long, py::array::c_style | py::array::forcecast>::ensure(obj);
  if (!a || a.ndim() != 1 || a.shape(0) != kTanks)
    throw py::value_error("valves must be a sequence of 6 ints");
  ftc::Valves u;
  for (int k = 0; k < kTanks; ++k) {
    const long long v = a.at(k);
    if (v != 0 && v != 1) throw py::value_error("valves must be 0 or 1");
    u[k] = static_cast<int>(v);
  }
  return u;
}

template <int N>
Eigen::Matrix<double, N, 1> Factors(const std::vector<double>& v, const char* what) {
  if (static_cast<int>(v.size()) != N) {
    throw py::value_error(std::string(what) + ": expected " + std::to_string(N) +
                          " numbers, got " + std::to_string(v.size()));
  }
  Eigen::Matrix<double, N, 1> out;
  for (int k = 0; k < N; ++k) {
    if (std::isnan(v[k]) || !(v[k] > 0))
      throw py::value_error(std::string(what) + ": factors must be > 0 (inf = healthy)");
    out[k] = v[k];
  }
  return out;
}

template <int N>
std::vector<double> ToList(const Eigen::Matrix<double, N, 1>& v) {
  return std::vector<double>(v.data(), v.data() + N);
}

py::dict ParamsDict(const ftc::PlantParams& p) {
  py::dict d;
  d["g"] = p.g;
  d["height"] = ToNumpy(p.height);
  d["area"] = ToNumpy(p.area);
  d["resistance"] = ToNumpy(p.resistance);
  d["pump"] = ToNumpy(p.pump);
  d["demand"] = ToNumpy(p.demand);
  return d;
}

// Keys not given keep their nominal values; unknown keys are an error.
ftc::PlantParams ParamsFromDict(const py::dict& d) {
  ftc::PlantParams p;
  for (const auto& item : d) {
    const std::string key = py::str(item.first);
    if (key == "g") {
      p.g = item.second.cast<double>();
    } else if (key == "height") {
      p.height = ToVec<kTanks>(item.second, "params['height']");
    } else if (key == "area") {
      p.area = ToVec<kTanks>(item.second, "params['area']");
    } else if (key == "resistance") {
      p.resistance = ToVec<kTanks>(item.second, "params['resistance']");
    } else if (key == "pump") {
      p.pump = ToVec<kTanks>(item.second, "params['pump']");
    } else if (key == "demand") {
      p.demand = ToVec<kEngines>(item.second, "params['demand']");
    } else {
      throw py::value_error("params: unknown key '" + key +
                            "' (known: g, height, area, resistance, pump, demand)");
    }
  }
  return p;
}

py::dict OutcomeDict(const ftc::StepOutcome& o) {
  py::dict d;
  d["level"] = ToNumpy(o.level);
  d["observed"] = ToNumpy(o.observed);
  d["valves"] = ToNumpy(o.valves);
  d["deficit"] = ToNumpy(o.deficit);
  d["age"] = o.age;
  d["step"] = o.step;
  d["episode"] = o.episode;
  d["terminal"] = o.terminal;
  d["truncated"] = o.truncated;
  d["evaluation"] = o.evaluation;
  return d;
}

std::string Repr(const py::handle& h) { return py::repr(h).cast<std::string>(); }

std::string ModeName(ftc::DegradationMode m) {
  return m == ftc::DegradationMode::kContinuous ? "continuous" : "stepwise";
}

// (K, L, 6) array of 0/1 valves -> K*L Valves, candidate-major.
std::vector<ftc::Valves> ToSequences(const py::handle& obj, int* k, int* l) {
  const auto a = py::array_t<long long, py::array::c_style | py::array::forcecast>::ensure(obj);
  if (!a || a.ndim() != 3 || a.shape(2) != kTanks)
    throw py::value_error("sequences must be an array of shape (K, L, 6)");
  *k = static_cast<int>(a.shape(0));
  *l = static_cast<int>(a.shape(1));
  const long long* data = a.data();
  std::vector<ftc::Valves> out(static_cast<std::size_t>(a.shape(0) * a.shape(1)));
  for (std::size_t n = 0; n < out.size(); ++n) {
    for (int i = 0; i < kTanks; ++i) {
      const long long v = data[n * kTanks + i];
      if (v != 0 && v != 1) throw py::value_error("sequences: valves must be 0 or 1");
      out[n][i] = static_cast<int>(v);
    }
  }
  return out;
}

// One params dict for every step, or a list of L dicts (one per step).
std::vector<ftc::PlantParams> ToParamsList(const py::handle& obj) {
  std::vector<ftc::PlantParams> out;
  if (py::isinstance<py::dict>(obj)) {
    out.push_back(ParamsFromDict(obj.cast<py::dict>()));
  } else {
    for (const auto& item : obj.cast<py::list>()) out.push_back(ParamsFromDict(item.cast<py::dict>()));
  }
  return out;
}

py::object RolloutToPython(const ftc::RolloutResult& r, int k, int l, bool details) {
  py::array_t<double> total(k);
  std::copy(r.total.begin(), r.total.end(), total.mutable_data());
  if (!details) return std::move(total);
  py::array_t<double> rewards({k, l});
  std::copy(r.rewards.begin(), r.rewards.end(), rewards.mutable_data());
  py::array_t<double> levels({k, l, static_cast<int>(kTanks)});
  double* lv = levels.mutable_data();
  for (std::size_t n = 0; n < r.levels.size(); ++n)
    for (int i = 0; i < kTanks; ++i) lv[n * kTanks + i] = r.levels[n][i];
  py::array_t<bool> terminal({k, l});
  std::copy(r.terminal.begin(), r.terminal.end(), terminal.mutable_data());
  py::dict d;
  d["total"] = total;
  d["rewards"] = rewards;
  d["levels"] = levels;
  d["terminal"] = terminal;
  d["integrated_steps"] = r.integrated_steps;
  d["exact_steps"] = r.exact_steps;
  d["shared_steps"] = r.shared_steps;
  return std::move(d);
}

py::object RunRollout(ftc::BatchRollout* rollout, const py::object& x0,
                      const py::object& sequences, const py::object& params, double dt,
                      bool details) {
  int k = 0, l = 0;
  const std::vector<ftc::Valves> seqs = ToSequences(sequences, &k, &l);
  const std::vector<ftc::PlantParams> plist = ToParamsList(params);
  const ftc::Vec6 x = ToVec<kTanks>(x0, "x0");
  ftc::RolloutResult r;
  {
    py::gil_scoped_release release;
    r = rollout->Run(x, seqs, k, l, plist, dt);
  }
  return RolloutToPython(r, k, l, details);
}

// (N, 6) float rows -> N Vec6 (levels); `what` names the argument in the error.
std::vector<ftc::Vec6> ToStates(const py::object& obj, const char* what) {
  const auto a = py::array_t<double, py::array::c_style | py::array::forcecast>::ensure(obj);
  if (!a || a.ndim() != 2 || a.shape(1) != kTanks)
    throw py::value_error(std::string(what) + " must be an array of shape (N, 6)");
  std::vector<ftc::Vec6> out(static_cast<std::size_t>(a.shape(0)));
  const double* d = a.data();
  for (std::size_t n = 0; n < out.size(); ++n)
    for (int i = 0; i < kTanks; ++i) out[n][i] = d[n * kTanks + i];
  return out;
}

// (T, 6) states and (T, 6) 0/1 valves, one step each -> (T, 6) next levels (NaN: refused).
py::array_t<double> StepEach(ftc::BatchRollout* rollout, const py::object& x,
                             const py::object& valves, const py::dict& params, double dt) {
  const std::vector<ftc::Vec6> states = ToStates(x, "x");
  const auto ua = py::array_t<long long, py::array::c_style | py::array::forcecast>::ensure(valves);
  if (!ua || ua.ndim() != 2 || ua.shape(1) != kTanks ||
      static_cast<std::size_t>(ua.shape(0)) != states.size())
    throw py::value_error("valves must be an array of shape (T, 6), as x");
  const std::size_t rows = states.size();
  std::vector<ftc::Valves> settings(rows);
  const long long* ud = ua.data();
  for (std::size_t n = 0; n < rows; ++n) {
    for (int i = 0; i < kTanks; ++i) {
      const long long v = ud[n * kTanks + i];
      if (v != 0 && v != 1) throw py::value_error("valves must be 0 or 1");
      settings[n][i] = static_cast<int>(v);
    }
  }
  const ftc::PlantParams p = ParamsFromDict(params);
  std::vector<ftc::Vec6> next;
  {
    py::gil_scoped_release release;
    next = rollout->StepEach(states, settings, p, dt);
  }
  py::array_t<double> out({static_cast<py::ssize_t>(rows), static_cast<py::ssize_t>(kTanks)});
  double* od = out.mutable_data();
  for (std::size_t n = 0; n < rows; ++n)
    for (int i = 0; i < kTanks; ++i) od[n * kTanks + i] = next[n][i];
  return out;
}

// (N, 6) levels, (N,) step counts -> (N,) summed rewards of the balance rule (-inf: refused).
py::array_t<double> RunBalanceRule(ftc::BatchRollout* rollout, const py::object& x,
                                   const py::object& steps, const py::dict& params,
                                   const py::object& stuck_mask, const py::object& stuck_state,
                                   double band, double dt) {
  const std::vector<ftc::Vec6> states = ToStates(x, "x");
  const py::array steps_array = py::array::ensure(steps);
  const char kind = steps_array ? steps_array.dtype().kind() : '?';
  if (!steps_array || (steps_array.size() > 0 && kind != 'i' && kind != 'u'))
    throw py::value_error("steps must be an array of integers");
  const auto sa = py::array_t<long long, py::array::c_style | py::array::forcecast>::ensure(steps);
  if (!sa || sa.ndim() != 1 || static_cast<std::size_t>(sa.shape(0)) != states.size())
    throw py::value_error("steps must be an array of shape (N,), one count per row of x");
  std::vector<int> counts(states.size());
  for (std::size_t n = 0; n < counts.size(); ++n) {
    const long long s = sa.data()[n];
    if (s < 0 || s > std::numeric_limits<int>::max())
      throw py::value_error("steps must be in [0, " +
                            std::to_string(std::numeric_limits<int>::max()) + "], got " +
                            std::to_string(s));
    counts[n] = static_cast<int>(s);
  }
  ftc::StuckValves stuck;
  if (!stuck_mask.is_none()) stuck.mask = ToValves(stuck_mask);
  if (!stuck_state.is_none()) stuck.state = ToValves(stuck_state);
  const ftc::PlantParams p = ParamsFromDict(params);
  std::vector<double> total;
  {
    py::gil_scoped_release release;
    total = rollout->RunBalanceRule(states, counts, p, stuck, band, dt);
  }
  py::array_t<double> out(static_cast<py::ssize_t>(total.size()));
  std::copy(total.begin(), total.end(), out.mutable_data());
  return out;
}

// Events <-> Python: a list of dicts as in the TOML file ({"at_step": 2600,
// "tank": 4, "factor": 2.0}, {"at_step": 3100, "stuck_valve": 2, "state": "open"};
// indices 1-based), validated by the file parser itself so both accept the same.
py::list EventsToPython(const std::vector<ftc::FaultEvent>& events) {
  py::list out;
  for (const ftc::FaultEvent& e : events) {
    py::dict d;
    d["at_step"] = e.at_step;
    switch (e.kind) {
      case ftc::FaultEvent::Kind::kTank: d["tank"] = e.index + 1; d["factor"] = e.factor; break;
      case ftc::FaultEvent::Kind::kEngine: d["engine"] = e.index + 1; d["factor"] = e.factor; break;
      case ftc::FaultEvent::Kind::kStuckValve:
        d["stuck_valve"] = e.index + 1;
        d["state"] = e.state ? "open" : "closed";
        break;
    }
    out.append(d);
  }
  return out;
}

std::string TomlValue(const py::handle& v) {
  if (py::isinstance<py::bool_>(v)) return v.cast<bool>() ? "true" : "false";
  if (py::isinstance<py::int_>(v)) return std::to_string(v.cast<long long>());
  if (py::isinstance<py::float_>(v)) {
    const double x = v.cast<double>();
    if (std::isnan(x)) return "nan";
    if (std::isinf(x)) return x > 0 ? "inf" : "-inf";
    std::ostringstream os;
    os.precision(17);
    os << std::showpoint << x;
    return os.str();
  }
  if (py::isinstance<py::str>(v)) {
    std::string text = "\"";
    for (const char c : v.cast<std::string>()) {
      if (c == '"' || c == '\\') text += '\\';
      if (static_cast<unsigned char>(c) < 0x20)
        throw py::value_error("events: control character in a string");
      text += c;
    }
    return text + "\"";
  }
  throw py::value_error("events: values must be int, float or str, got " + Repr(v));
}

std::vector<ftc::FaultEvent> EventsFromPython(const py::handle& obj) {
  std::string toml;
  for (const auto& item : obj.cast<py::list>()) {
    toml += "[[event]]\n";
    for (const auto& [k, v] : item.cast<py::dict>()) {
      const std::string key = py::str(k);
      for (const char c : key)
        if (!(std::isalnum(static_cast<unsigned char>(c)) || c == '_'))
          throw py::value_error("events: bad key " + Repr(k));
      toml += key + " = " + TomlValue(v) + "\n";
    }
  }
  return ftc::ParseScenario(toml, "Scenario.events").events;
}

}  // namespace

PYBIND11_MODULE(_core, m) {
  m.doc() = "C++ physics core of the fuel-transfer plant (CVODE, hybrid dynamics).";
  py::register_exception<ftc::ScenarioError>(m, "ScenarioError", PyExc_ValueError);

  py::class_<ftc::FaultScenario>(m, "Scenario", "Fault scenario (default: nominal, healthy).")
      .def(py::init<>())
      .def_readwrite("name", &ftc::FaultScenario::name)
      .def_property(
          "tank_factor", [](const ftc::FaultScenario& s) { return ToList(s.tank_factor); },
          [](ftc::FaultScenario& s, const std::vector<double>& v) {
            s.tank_factor = Factors<kTanks>(v, "tank_factor");
          },
          "D_T per tank (6 floats, inf = healthy)")
      .def_property(
          "engine_factor", [](const ftc::FaultScenario& s) { return ToList(s.engine_factor); },
          [](ftc::FaultScenario& s, const std::vector<double>& v) {
            s.engine_factor = Factors<kEngines>(v, "engine_factor");
          },
          "D_E per engine (2 floats, inf = healthy)")
      .def_property(
          "mode", [](const ftc::FaultScenario& s) { return ModeName(s.mode); },
          [](ftc::FaultScenario& s, const std::string& v) {
            if (v == "stepwise") {
              s.mode = ftc::DegradationMode::kStepwise;
            } else if (v == "continuous") {
              s.mode = ftc::DegradationMode::kContinuous;
            } else {
              throw py::value_error("mode must be 'stepwise' or 'continuous', got '" + v + "'");
            }
          },
          "'stepwise' (age = interval index) or 'continuous'")
      .def_property(
          "noise_std", [](const ftc::FaultScenario& s) { return s.noise_std; },
          [](ftc::FaultScenario& s, double v) {
            if (!std::isfinite(v) || v < 0) throw py::value_error("noise_std must be >= 0");
            s.noise_std = v;
          },
          "sensor noise on published levels, m")
      .def_readwrite("random_start", &ftc::FaultScenario::random_start)
      .def_property(
          "steps_per_interval", [](const ftc::FaultScenario& s) { return s.steps_per_interval; },
          [](ftc::FaultScenario& s, int v) {
            if (v <= 0) throw py::value_error("steps_per_interval must be > 0");
            s.steps_per_interval = v;
          },
          "control steps per degradation interval (t_online)")
      .def_property(
          "events", [](const ftc::FaultScenario& s) { return EventsToPython(s.events); },
          [](ftc::FaultScenario& s, const py::object& v) { s.events = EventsFromPython(v); },
          "abrupt faults, sorted by at_step: a list of dicts as the file's [[event]] tables "
          "(at_step, and tank + factor, engine + factor, or stuck_valve + state; 1-based); "
          "assigning validates as the file parser does (ScenarioError)")
      .def("__repr__", [](const ftc::FaultScenario& s) {
        return "Scenario(name=" + Repr(py::str(s.name)) +
               ", tank_factor=" + Repr(py::cast(ToList(s.tank_factor))) +
               ", engine_factor=" + Repr(py::cast(ToList(s.engine_factor))) + ", mode='" +
               ModeName(s.mode) + "', noise_std=" + Repr(py::float_(s.noise_std)) +
               ", random_start=" + (s.random_start ? "True" : "False") +
               ", steps_per_interval=" + std::to_string(s.steps_per_interval) +
               (s.events.empty() ? "" : ", events=" + Repr(EventsToPython(s.events))) + ")";
      });

  m.def("load_scenario", &ftc::LoadScenario, py::arg("path"),
        "Read a scenario TOML file; raises ScenarioError (a ValueError) naming file and key.");
  m.def("parse_scenario", &ftc::ParseScenario, py::arg("text"), py::arg("source_name"),
        "Parse scenario TOML text; source_name is used in error messages.");

  py::class_<ftc::Plant>(m, "Plant", "The plant: episodes, degradation, noise, CVODE steps.")
      .def(py::init([](const ftc::FaultScenario& s, std::uint64_t seed, const std::string& method) {
             ftc::StepMethod m = ftc::StepMethod::kCvode;
             try {
               m = ftc::ParseStepMethod(method);
             } catch (const std::invalid_argument& e) {
               throw py::value_error(e.what());
             }
             return std::make_unique<ftc::Plant>(s, seed, ftc::PlantParams{},
                                                 ftc::IntegratorOptions{}, m);
           }),
           py::arg("scenario"), py::arg("seed"), py::arg("method") = "cvode",
           "method: 'cvode' (the plant process's) or 'closed_form' (plant.h StepMethod)")
      .def("reset", &ftc::Plant::Reset, "Start a new operating episode (full tanks).")
      .def("reset_evaluation", &ftc::Plant::ResetEvaluation,
           "Start an evaluation episode (age frozen, steps not counted).")
      .def(
          "step",
          [](ftc::Plant& p, const py::object& valves) {
            return OutcomeDict(p.Step(ToValves(valves)));
          },
          py::arg("valves"), "Apply 6 valves (0/1) for one 1 s step; returns the outcome dict.")
      .def("last", [](const ftc::Plant& p) { return OutcomeDict(p.last()); })
      .def_property_readonly("operating_steps", &ftc::Plant::operating_steps)
      .def_property_readonly("current_age", &ftc::Plant::current_age)
      .def("set_operating_steps", &ftc::Plant::SetOperatingSteps, py::arg("steps"),
           "Resume at an operating age: the next step is taken at AgeAt(steps).")
      .def_property_readonly("scenario", &ftc::Plant::scenario)
      .def_property_readonly("step_in_force", &ftc::Plant::step_in_force,
                             "operating step whose parameters and stuck valves the next step "
                             "uses (frozen at the last operating step's in evaluation)")
      .def(
          "params_at", [](const ftc::Plant& p, double age) { return ParamsDict(p.ParamsAt(age)); },
          py::arg("age"), "The scenario's factors at an age (events not applied).")
      .def(
          "params_at_step",
          [](const ftc::Plant& p, std::int64_t steps) { return ParamsDict(p.ParamsAtStep(steps)); },
          py::arg("operating_steps"),
          "Parameters of the step after `operating_steps` operating steps (events applied).");

  m.def(
      "degraded_params",
      [](const ftc::FaultScenario& s, double age) {
        return ParamsDict(ftc::DegradedParams(ftc::PlantParams{}, s, age));
      },
      py::arg("scenario"), py::arg("age"),
      "Nominal parameters degraded to an age (intervals), with the scenario's own factors "
      "(events not applied; see params_at_step).");
  m.def(
      "params_at_step",
      [](const ftc::FaultScenario& s, std::int64_t operating_steps) {
        if (operating_steps < 0) throw py::value_error("operating_steps must be >= 0");
        return ParamsDict(ftc::DegradedParamsAtStep(ftc::PlantParams{}, s, operating_steps));
      },
      py::arg("scenario"), py::arg("operating_steps"),
      "Parameters in force during the step after `operating_steps` operating steps: the "
      "factors with the events of at_step <= operating_steps applied, at age_at(...). "
      "Equals degraded_params(scenario, age_at(...)) without events.");
  m.def(
      "stuck_valves_at_step",
      [](const ftc::FaultScenario& s, std::int64_t operating_steps) {
        if (operating_steps < 0) throw py::value_error("operating_steps must be >= 0");
        const ftc::StuckValves v = ftc::StuckValvesAtStep(s, operating_steps);
        py::array_t<bool> mask(kTanks);
        for (int i = 0; i < kTanks; ++i) mask.mutable_at(i) = v.mask[i] != 0;
        return py::make_tuple(mask, ToNumpy(v.state));
      },
      py::arg("scenario"), py::arg("operating_steps"),
      "(mask (6,) bool, state (6,) int 0/1) of the valves stuck during the step after "
      "`operating_steps` operating steps; state is 0 where not stuck.");

  m.def(
      "integrate_step",
      [](const py::object& x0, const py::object& valves, const py::dict& params, double dt) {
        const ftc::PlantParams p = ParamsFromDict(params);
        ftc::StepIntegrator integrator;
        const ftc::StepResult r =
            integrator.Step(ToVec<kTanks>(x0, "x0"), ToValves(valves), p, dt);
        py::dict d;
        d["x"] = ToNumpy(r.x);
        d["supplied"] = ToNumpy(r.supplied);
        d["deficit"] = ToNumpy(r.deficit);
        d["events"] = r.events;
        return d;
      },
      py::arg("x0"), py::arg("valves"), py::arg("params"), py::arg("dt") = 1.0,
      "Integrate one step from x0 with valves held; supplied/deficit in m^3.");

  m.def(
      "reward",
      [](const py::object& x_next, const py::object& valves) {
        const ftc::RewardTerms t = ftc::ComputeReward(ToVec<kTanks>(x_next, "x_next"),
                                                      ToValves(valves), ftc::PlantParams{});
        py::dict d;
        d["reward"] = t.reward;
        d["cg"] = t.cg;
        d["spread"] = t.spread;
        d["activity"] = t.activity;
        return d;
      },
      py::arg("x_next"), py::arg("valves"),
      "Reward terms at the levels after a step (nominal areas).");

  m.def(
      "compute_flows",
      [](const py::object& x, const py::object& valves, const py::dict& params) {
        const ftc::PlantParams p = ParamsFromDict(params);
        const ftc::Vec6 xv = ToVec<kTanks>(x, "x");
        const ftc::Valves u = ToValves(valves);
        const ftc::Flows f = ftc::ComputeFlows(xv, u, p, ftc::ComputeMode(xv, u, p));
        py::dict d;
        d["conduit"] = ToNumpy(f.conduit);
        d["supply"] = ToNumpy(f.supply);
        d["deficit"] = ToNumpy(f.deficit);
        return d;
      },
      py::arg("x"), py::arg("valves"), py::arg("params"),
      "Flows (m^3/s) at x with the mode computed at x.");

  const char* rollout_doc =
      "Summed rewards (K,) of K candidate valve sequences (K, L, 6) of 0/1 from levels x0 "
      "(6,) m, under params (one dict, or a list of L dicts: step t under params[t]); dt s "
      "per step. A terminal step (Plant::IsTerminal) resets to full tanks, as the plant "
      "does. details=True returns a dict: total (K,), rewards (K, L), levels (K, L, 6) "
      "after each step before any reset, terminal (K, L), and step counts.";
  py::class_<ftc::BatchRollout>(m, "BatchRollout",
                                "Reusable batch rollouts (one CVODE integrator, kept warm).")
      .def(py::init([](bool exact_idle_conduit, bool share_prefixes, double rtol, double atol,
                       bool exact_active_conduit) {
             ftc::RolloutOptions o;
             o.exact_idle_conduit = exact_idle_conduit;
             o.share_prefixes = share_prefixes;
             o.exact_active_conduit = exact_active_conduit;
             ftc::IntegratorOptions io;
             io.rtol = rtol;
             io.atol = atol;
             return std::make_unique<ftc::BatchRollout>(io, o);
           }),
           py::arg("exact_idle_conduit") = true, py::arg("share_prefixes") = true,
           py::arg("rtol") = ftc::IntegratorOptions{}.rtol,
           py::arg("atol") = ftc::IntegratorOptions{}.atol,
           py::arg("exact_active_conduit") = false,
           "rtol/atol: CVODE tolerances of the rollouts (default: the plant's); "
           "exact_active_conduit: steps with two or more valves open in closed form too "
           "(linear_step.h), CVODE only where a tank is pinned")
      .def("run", &RunRollout, py::arg("x0"), py::arg("sequences"), py::arg("params"),
           py::arg("dt") = 1.0, py::arg("details") = false, rollout_doc)
      .def("step_each", &StepEach, py::arg("x"), py::arg("valves"), py::arg("params"),
           py::arg("dt") = 1.0,
           "Levels (T, 6) m after one step of dt s from each row of x (T, 6) with the row's "
           "valves (T, 6) of 0/1, under params (one dict); no episode rule. A row the "
           "integrator refuses (chattering) is NaN; rows run in order, as T one-step run() "
           "calls would (bit-identical).")
      .def("run_balance_rule", &RunBalanceRule, py::arg("x"), py::arg("steps"),
           py::arg("params"), py::arg("stuck_mask") = py::none(),
           py::arg("stuck_state") = py::none(), py::arg("band") = 0.1, py::arg("dt") = 1.0,
           "Summed rewards (N,) of the balance rule in closed loop, row n from levels x[n] "
           "(N, 6) m for steps[n] steps of dt s under params (one dict): each step's valves "
           "from the levels the step before left (the fullest tank of the heavy wing and the "
           "emptiest of the light one open where |cg| > band). Valves of stuck_mask (6,) 0/1 "
           "stay at stuck_state (6,) and the reward charges the commanded ones; a terminal "
           "step resets to full tanks, as run() does. A row the integrator refuses is -inf.");
  m.def(
      "batch_rollout",
      [](const py::object& x0, const py::object& sequences, const py::object& params, double dt,
         bool details) {
        ftc::BatchRollout rollout;
        return RunRollout(&rollout, x0, sequences, params, dt, details);
      },
      py::arg("x0"), py::arg("sequences"), py::arg("params"), py::arg("dt") = 1.0,
      py::arg("details") = false, rollout_doc);
  m.def(
      "balance_valves",
      [](const py::object& levels, const py::dict& params, double band) {
        const std::vector<ftc::Vec6> rows = ToStates(levels, "levels");
        const ftc::PlantParams p = ParamsFromDict(params);
        py::array_t<std::int8_t> out({static_cast<py::ssize_t>(rows.size()),
                                      static_cast<py::ssize_t>(kTanks)});
        std::int8_t* od = out.mutable_data();
        for (std::size_t n = 0; n < rows.size(); ++n) {
          const ftc::Valves u = ftc::BalanceValves(rows[n], p, band);
          for (int i = 0; i < kTanks; ++i) od[n * kTanks + i] = static_cast<std::int8_t>(u[i]);
        }
        return out;
      },
      py::arg("levels"), py::arg("params"), py::arg("band") = 0.1,
      "The balance rule's valves (N, 6) int8 for levels (N, 6) m (the C++ rule that "
      "BatchRollout.run_balance_rule steps; ftc.control.agents.balance is its reference).");
  m.def(
      "age_at",
      [](const ftc::FaultScenario& s, std::int64_t operating_steps) {
        return ftc::AgeAt(s, operating_steps);
      },
      py::arg("scenario"), py::arg("operating_steps"),
      "Age (intervals) in force during the step after `operating_steps` counted steps.");
  BindPool(m);
}
