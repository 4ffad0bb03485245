// Python bindings of the plant pool and the scenario distribution (part of
// ftc._core; bindings.cpp calls BindPool). The pool writes into NumPy arrays
// the caller binds once (bind_outputs): their buffers, checked for dtype,
// shape, C order and writeability, are written in place by the C++ threads
// with the GIL released; step() checks its actions (int8, N x 6, 0 or 1)
// before any env moves, so a refused call steps nothing.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "plant/core/pool.h"
#include "plant/core/scenario_distribution.h"

namespace py = pybind11;

namespace {

using ftc::kTanks;

std::string DtypeName(const py::array& a) { return py::str(a.dtype()).cast<std::string>(); }

std::string ShapeText(const py::array& a) {
  std::string s = "(";
  for (py::ssize_t k = 0; k < a.ndim(); ++k) s += (k ? ", " : "") + std::to_string(a.shape(k));
  return s + (a.ndim() == 1 ? ",)" : ")");
}

// The buffer of `obj` if it is a writeable C-ordered array of dtype T and shape
// (n,) or (n, 6); else a one-line ValueError naming it.
template <typename T>
T* Buffer(const py::handle& obj, const char* name, py::ssize_t n, bool rows_of_six,
          std::vector<py::object>* keep) {
  const std::string want = std::string(py::str(py::dtype::of<T>())) + " of shape (" +
                           std::to_string(n) + (rows_of_six ? ", 6)" : ",)");
  if (!py::isinstance<py::array>(obj))
    throw py::value_error(std::string("PlantPool.bind_outputs: ") + name + " must be a " +
                          "numpy array, " + want + ", got " +
                          py::str(py::type::of(obj)).cast<std::string>());
  py::array a = py::reinterpret_borrow<py::array>(obj);
  const bool shape_ok = rows_of_six ? (a.ndim() == 2 && a.shape(0) == n && a.shape(1) == kTanks)
                                    : (a.ndim() == 1 && a.shape(0) == n);
  if (!a.dtype().is(py::dtype::of<T>()) || !shape_ok)
    throw py::value_error(std::string("PlantPool.bind_outputs: ") + name + " must be " + want +
                          ", got " + DtypeName(a) + " of shape " + ShapeText(a));
  if (!(a.flags() & py::array::c_style) || !a.writeable())
    throw py::value_error(std::string("PlantPool.bind_outputs: ") + name +
                          " must be C-contiguous and writeable");
  keep->push_back(a);
  return static_cast<T*>(a.mutable_data());
}

// The pool and the arrays it writes into (kept alive while bound).
struct PyPool {
  std::unique_ptr<ftc::PlantPool> pool;
  std::vector<py::object> keep;
  ftc::PoolOutput out;
  bool bound = false;

  void Require() const {
    if (!bound) throw py::value_error("PlantPool: call bind_outputs(...) before reset or step");
  }
};

std::vector<ftc::FaultScenario> Scenarios(const py::handle& obj) {
  std::vector<ftc::FaultScenario> out;
  for (const auto& item : obj.cast<py::list>()) out.push_back(item.cast<ftc::FaultScenario>());
  return out;
}

ftc::ScenarioDistribution::Range ToRange(const py::handle& obj, const char* name) {
  const auto v = obj.cast<std::vector<double>>();
  if (v.size() != 2)
    throw py::value_error(std::string("ScenarioDistribution: ") + name +
                          " must be [low, high], got " + std::to_string(v.size()) + " numbers");
  return {v[0], v[1]};
}

// invalid_argument from the core -> ValueError, one line as thrown
template <typename F>
auto Checked(F&& f) -> decltype(f()) {
  try {
    return f();
  } catch (const std::invalid_argument& e) {
    throw py::value_error(e.what());
  }
}

}  // namespace

void BindPool(py::module_& m) {
  using D = ftc::ScenarioDistribution;
  py::class_<D>(m, "ScenarioDistribution",
                "A declared distribution of fault scenarios (scenario_distribution.h): "
                "probabilities and [low, high] ranges; draw(count, seed) gives Scenarios.")
      .def(py::init([](const py::kwargs& kwargs) {
        D d;
        for (const auto& [k, v] : kwargs) {
          const std::string key = py::str(k);
          if (key == "mode") {
            const auto name = v.cast<std::string>();
            if (name != "stepwise" && name != "continuous")
              throw py::value_error("ScenarioDistribution: mode must be 'stepwise' or "
                                    "'continuous', got '" + name + "'");
            d.mode = name == "continuous" ? ftc::DegradationMode::kContinuous
                                          : ftc::DegradationMode::kStepwise;
          } else if (key == "steps_per_interval") { d.steps_per_interval = v.cast<int>();
          } else if (key == "life_intervals") { d.life_intervals = v.cast<int>();
          } else if (key == "tank_probability") { d.tank_probability = v.cast<double>();
          } else if (key == "tank_factor") { d.tank_factor = ToRange(v, "tank_factor");
          } else if (key == "engine_probability") { d.engine_probability = v.cast<double>();
          } else if (key == "engine_factor") { d.engine_factor = ToRange(v, "engine_factor");
          } else if (key == "dead_pump_probability") { d.dead_pump_probability = v.cast<double>();
          } else if (key == "event_probability") { d.event_probability = v.cast<double>();
          } else if (key == "event_factor") { d.event_factor = ToRange(v, "event_factor");
          } else if (key == "stuck_valve_probability") {
            d.stuck_valve_probability = v.cast<double>();
          } else if (key == "noise_probability") { d.noise_probability = v.cast<double>();
          } else if (key == "noise_std") { d.noise_std = ToRange(v, "noise_std");
          } else {
            throw py::value_error("ScenarioDistribution: unknown field '" + key + "'");
          }
        }
        Checked([&] { d.Validate(); return 0; });
        return d;
      }))
      .def_property_readonly("mode", [](const D& d) {
        return d.mode == ftc::DegradationMode::kContinuous ? "continuous" : "stepwise";
      })
      .def_readonly("steps_per_interval", &D::steps_per_interval)
      .def_readonly("life_intervals", &D::life_intervals)
      .def_readonly("tank_probability", &D::tank_probability)
      .def_readonly("tank_factor", &D::tank_factor)
      .def_readonly("engine_probability", &D::engine_probability)
      .def_readonly("engine_factor", &D::engine_factor)
      .def_readonly("dead_pump_probability", &D::dead_pump_probability)
      .def_readonly("event_probability", &D::event_probability)
      .def_readonly("event_factor", &D::event_factor)
      .def_readonly("stuck_valve_probability", &D::stuck_valve_probability)
      .def_readonly("noise_probability", &D::noise_probability)
      .def_readonly("noise_std", &D::noise_std)
      .def("check",
           [](const D& d, const ftc::FaultScenario& s) {
             Checked([&] { d.Check(s); return 0; });
           },
           py::arg("scenario"),
           "Raise ValueError (one line) unless the distribution can draw this scenario.")
      .def("draw", [](const D& d, int count, std::uint64_t seed) {
             return Checked([&] { return ftc::DrawScenarios(d, count, seed); });
           }, py::arg("count"), py::arg("seed"),
           "`count` Scenarios drawn from `seed` (scenario n from its own stream).");

  py::class_<PyPool>(m, "PlantPool",
                     "N plants stepped by one call across a thread pool (pool.h).")
      .def(py::init([](const py::object& scenarios, const std::vector<std::uint64_t>& seeds,
                       const std::string& method, int threads, const std::string& autoreset,
                       int life_intervals, const D* distribution) {
             auto self = std::make_unique<PyPool>();
             ftc::PoolOptions o;
             o.method = Checked([&] { return ftc::ParseStepMethod(method); });
             o.autoreset = Checked([&] { return ftc::ParseAutoreset(autoreset); });
             o.threads = threads;
             o.life_intervals = life_intervals;
             const auto list = Scenarios(scenarios);
             self->pool = Checked(
                 [&] { return std::make_unique<ftc::PlantPool>(list, seeds, o, distribution); });
             return self;
           }),
           py::arg("scenarios"), py::arg("seeds"), py::arg("method") = "closed_form",
           py::arg("threads") = 0, py::arg("autoreset") = "next_step",
           py::arg("life_intervals") = 0, py::arg("distribution") = nullptr,
           "scenarios: a list of N Scenarios; seeds: N ints; method: 'closed_form' or 'cvode' "
           "(plant.h StepMethod); threads: 0 = every core; autoreset: 'next_step' or "
           "'same_step'; life_intervals > 0: renew a plant after that many intervals "
           "(a scenario drawn from `distribution` if given)")
      .def_property_readonly("num_envs", [](const PyPool& p) { return p.pool->size(); })
      .def_property_readonly("threads", [](const PyPool& p) { return p.pool->threads(); })
      .def("bind_outputs",
           [](PyPool& p, const py::object& obs, const py::object& reward,
              const py::object& terminated, const py::object& truncated, const py::object& age,
              const py::object& episode_step, const py::object& cg, const py::object& spread,
              const py::object& activity, const py::object& final_obs,
              const py::object& final_mask, const py::object& valves) {
             const py::ssize_t n = p.pool->size();
             std::vector<py::object> keep;
             ftc::PoolOutput out;
             out.obs = Buffer<float>(obs, "obs", n, true, &keep);
             out.reward = Buffer<double>(reward, "reward", n, false, &keep);
             out.terminated = Buffer<bool>(terminated, "terminated", n, false, &keep);
             out.truncated = Buffer<bool>(truncated, "truncated", n, false, &keep);
             out.age = Buffer<double>(age, "age", n, false, &keep);
             out.episode_step = Buffer<std::int64_t>(episode_step, "episode_step", n, false, &keep);
             out.cg = Buffer<double>(cg, "cg", n, false, &keep);
             out.spread = Buffer<double>(spread, "spread", n, false, &keep);
             out.activity = Buffer<double>(activity, "activity", n, false, &keep);
             out.final_obs = Buffer<float>(final_obs, "final_obs", n, true, &keep);
             out.final_mask = Buffer<bool>(final_mask, "final_mask", n, false, &keep);
             if (!valves.is_none())
               out.valves = Buffer<std::int8_t>(valves, "valves", n, true, &keep);
             p.keep = std::move(keep);
             p.out = out;
             p.bound = true;
           },
           py::arg("obs"), py::arg("reward"), py::arg("terminated"), py::arg("truncated"),
           py::arg("age"), py::arg("episode_step"), py::arg("cg"), py::arg("spread"),
           py::arg("activity"), py::arg("final_obs"), py::arg("final_mask"),
           py::arg("valves") = py::none(),
           "Arrays every reset and step writes into: obs (N, 6) float32, reward float64, "
           "terminated and truncated bool, age float64, episode_step int64, cg, spread, "
           "activity float64, final_obs (N, 6) float32, final_mask bool (N,), and if given "
           "valves (N, 6) int8: the valves applied during the step just taken (stuck ones "
           "as they stayed; 0 after a reset), as the plant's state message publishes them")
      .def("reset", [](PyPool& p) {
             p.Require();
             py::gil_scoped_release release;
             p.pool->Reset(p.out);
           }, "A new episode in every env at its age (renewing plants past their life).")
      .def("reseed",
           [](PyPool& p, const py::object& scenarios, const std::vector<std::uint64_t>& seeds) {
             const auto list = Scenarios(scenarios);
             Checked([&] { p.pool->Reseed(list, seeds); return 0; });
           },
           py::arg("scenarios"), py::arg("seeds"), "Fresh plants (age 0); reset() next.")
      .def("step",
           [](PyPool& p, const py::object& actions) {
             p.Require();
             const py::ssize_t n = p.pool->size();
             if (!py::isinstance<py::array>(actions))
               throw py::value_error("PlantPool.step: actions must be an int8 numpy array of "
                                     "shape (" + std::to_string(n) + ", 6)");
             py::array a = py::reinterpret_borrow<py::array>(actions);
             if (!a.dtype().is(py::dtype::of<std::int8_t>()) || a.ndim() != 2 ||
                 a.shape(0) != n || a.shape(1) != kTanks || !(a.flags() & py::array::c_style))
               throw py::value_error("PlantPool.step: actions must be C-ordered int8 of shape (" +
                                     std::to_string(n) + ", 6), got " + DtypeName(a) +
                                     " of shape " + ShapeText(a));
             const auto* u = static_cast<const std::int8_t*>(a.data());
             for (py::ssize_t k = 0; k < n * kTanks; ++k)
               if (u[k] != 0 && u[k] != 1)
                 throw py::value_error("PlantPool.step: actions must be 0 or 1, got " +
                                       std::to_string(u[k]) + " at env " +
                                       std::to_string(k / kTanks) + ", valve " +
                                       std::to_string(k % kTanks));
             py::gil_scoped_release release;
             p.pool->Step(u, p.out);
           },
           py::arg("actions"),
           "One step of every env with actions (N, 6) int8 of 0/1; writes the bound arrays.")
      .def("operating_steps", [](const PyPool& p, int i) {
             return p.pool->plant(i).operating_steps();
           }, py::arg("env"))
      .def("scenario", [](const PyPool& p, int i) { return p.pool->plant(i).scenario(); },
           py::arg("env"));
}
