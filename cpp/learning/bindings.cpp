// Python bindings of the learning kernels (module ftc._learn): arrays in,
// shapes checked here with messages that name the argument.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "learning/ppo_update.h"
#include "learning/tanh_mlp.h"

namespace py = pybind11;

namespace {

template <typename T>
using Array = py::array_t<T, py::array::c_style>;

std::string Shape(const py::array& a) {
  std::string s = "(";
  for (py::ssize_t d = 0; d < a.ndim(); ++d) s += (d ? ", " : "") + std::to_string(a.shape(d));
  return s + (a.ndim() == 1 ? ",)" : ")");
}

void Require(bool ok, const std::string& what) {
  if (!ok) throw py::value_error(what);
}

py::tuple Distill(py::array params, const std::vector<int>& trunk, const std::vector<int>& head,
                  const Array<float>& x, const Array<float>& y, const py::object& weights,
                  const Array<std::int64_t>& orders, int minibatch, double lr,
                  double max_grad_norm, double stop_loss) {
  Require(trunk.size() >= 2 && head.size() >= 2 && trunk.back() == head.front(),
          "distill: trunk and head widths must chain (trunk[-1] == head[0])");
  const std::size_t size = ftc::learn::TanhChain::Size(trunk) + ftc::learn::TanhChain::Size(head);
  // updated in place, so never converted (a converted copy would drop the update)
  Require(params.dtype().is(py::dtype::of<float>()) && params.ndim() == 1 &&
              static_cast<std::size_t>(params.shape(0)) >= size,
          "distill: params must be a float32 vector of at least " + std::to_string(size) +
              " entries, got " + std::string(py::str(params.dtype())) + " " + Shape(params));
  Require(params.writeable() && (params.flags() & py::array::c_style),
          "distill: params must be a writable contiguous array (it is updated in place)");
  Require(x.ndim() == 2 && x.shape(1) == trunk.front(),
          "distill: x must be (N, " + std::to_string(trunk.front()) + "), got " + Shape(x));
  const auto n = static_cast<int>(x.shape(0));
  Require(y.ndim() == 2 && y.shape(0) == n && y.shape(1) == head.back(),
          "distill: y must be (" + std::to_string(n) + ", " + std::to_string(head.back()) +
              "), got " + Shape(y));
  Require(orders.ndim() == 2 && orders.shape(1) == n,
          "distill: orders must be (epochs, " + std::to_string(n) + "), got " + Shape(orders));
  Array<float> w;
  if (!weights.is_none()) {
    w = weights.cast<Array<float>>();
    Require(w.ndim() == 1 && w.shape(0) == n,
            "distill: weights must be (" + std::to_string(n) + ",), got " + Shape(w));
  }
  ftc::learn::DistillOptions options;
  options.minibatch = minibatch;
  options.lr = lr;
  options.max_grad_norm = max_grad_norm;
  options.stop_loss = stop_loss;
  float* p = static_cast<float*>(params.mutable_data());
  const float* w_data = weights.is_none() ? nullptr : w.data();
  ftc::learn::DistillResult r;
  {
    py::gil_scoped_release release;
    r = ftc::learn::Distill(p, trunk, head, x.data(), y.data(), w_data, n, orders.data(),
                            static_cast<int>(orders.shape(0)), options);
  }
  return py::make_tuple(r.last_loss, r.epochs, r.steps);
}

// A float32 C-contiguous writable array of exactly `size` entries: updated in
// place, so never converted (a converted copy would drop the update).
float* InPlace(const py::array& a, std::size_t size, const std::string& what) {
  Require(a.dtype().is(py::dtype::of<float>()) && a.ndim() == 1 &&
              static_cast<std::size_t>(a.shape(0)) == size,
          what + " must be a float32 vector of " + std::to_string(size) + " entries, got " +
              std::string(py::str(a.dtype())) + " " + Shape(a));
  Require(a.writeable() && (a.flags() & py::array::c_style),
          what + " must be a writable contiguous array (it is updated in place)");
  return static_cast<float*>(py::array(a).mutable_data());
}

ftc::learn::ActorCriticShape MakeShape(const std::vector<int>& trunk,
                                       const std::vector<int>& policy,
                                       const std::vector<int>& value) {
  ftc::learn::ActorCriticShape shape{trunk, policy, value};
  try {
    shape.Check();
  } catch (const std::invalid_argument& e) {
    throw py::value_error(e.what());
  }
  return shape;
}

py::tuple PpoEpoch(py::array params, py::array adam_m, py::array adam_v, std::int64_t adam_t,
                   const std::vector<int>& trunk, const std::vector<int>& policy,
                   const std::vector<int>& value, const Array<float>& obs,
                   const Array<float>& actions, const Array<float>& old_logprobs,
                   const Array<float>& advantages, const Array<float>& returns,
                   const Array<std::int64_t>& order, int minibatch, double clip_coef,
                   double ent_coef, double vf_coef, double max_grad_norm, bool norm_adv,
                   double lr, double beta1, double beta2, double eps) {
  const auto shape = MakeShape(trunk, policy, value);
  const std::size_t size = shape.Size();
  float* p = InPlace(params, size, "ppo_epoch: params");
  float* m = InPlace(adam_m, size, "ppo_epoch: adam_m");
  float* v = InPlace(adam_v, size, "ppo_epoch: adam_v");
  Require(obs.ndim() == 2 && obs.shape(1) == trunk.front(),
          "ppo_epoch: obs must be (N, " + std::to_string(trunk.front()) + "), got " + Shape(obs));
  const auto rows = static_cast<int>(obs.shape(0));
  const std::string n_str = std::to_string(rows);
  Require(actions.ndim() == 2 && actions.shape(0) == rows && actions.shape(1) == policy.back(),
          "ppo_epoch: actions must be (" + n_str + ", " + std::to_string(policy.back()) +
              "), got " + Shape(actions));
  for (const auto& [a, name] : {std::pair{&old_logprobs, "old_logprobs"},
                                {&advantages, "advantages"}, {&returns, "returns"}})
    Require(a->ndim() == 1 && a->shape(0) == rows,
            std::string("ppo_epoch: ") + name + " must be (" + n_str + ",), got " + Shape(*a));
  Require(order.ndim() == 1, "ppo_epoch: order must be a vector of row indices, got " +
                                 Shape(order));
  Require(minibatch > 0, "ppo_epoch: minibatch must be positive");
  ftc::learn::PpoOptions options;
  options.minibatch = minibatch;
  options.clip_coef = clip_coef;
  options.ent_coef = ent_coef;
  options.vf_coef = vf_coef;
  options.max_grad_norm = max_grad_norm;
  options.norm_adv = norm_adv;
  options.lr = lr;
  options.beta1 = beta1;
  options.beta2 = beta2;
  options.eps = eps;
  ftc::learn::PpoEpochResult r;
  try {
    py::gil_scoped_release release;
    r = ftc::learn::PpoEpoch(p, m, v, &adam_t, shape, obs.data(), actions.data(),
                             old_logprobs.data(), advantages.data(), returns.data(), rows,
                             order.data(), static_cast<int>(order.shape(0)), options);
  } catch (const std::invalid_argument& e) {
    throw py::value_error(std::string("ppo_epoch: ") + e.what());
  }
  return py::make_tuple(Array<double>(static_cast<py::ssize_t>(r.approx_kl.size()),
                                      r.approx_kl.data()),
                        Array<double>(static_cast<py::ssize_t>(r.clipfrac.size()),
                                      r.clipfrac.data()),
                        r.policy_loss, r.value_loss, adam_t);
}

// ftc::learn::Actor over arrays it keeps alive (torch's parameter memory).
class PyActor {
 public:
  PyActor(const std::vector<int>& trunk, const std::vector<int>& policy,
          const std::vector<int>& value, const py::list& layers)
      : shape_(MakeShape(trunk, policy, value)) {
    std::vector<const float*> pointers;
    std::vector<std::vector<int>> widths{trunk, policy, value};
    std::size_t i = 0;
    for (const auto& w : widths)
      for (std::size_t l = 0; l + 1 < w.size(); ++l, i += 2) {
        Require(i + 1 < layers.size(), "Actor: expected a weight and a bias for each layer");
        const py::array weight = layers[i], bias = layers[i + 1];
        Require(weight.dtype().is(py::dtype::of<float>()) && weight.ndim() == 2 &&
                    weight.shape(0) == w[l + 1] && weight.shape(1) == w[l] &&
                    (weight.flags() & py::array::c_style),
                "Actor: layer weight " + std::to_string(i / 2) + " must be a contiguous float32 (" +
                    std::to_string(w[l + 1]) + ", " + std::to_string(w[l]) +
                    ") array (torch's (out, in)), got " + Shape(weight));
        Require(bias.dtype().is(py::dtype::of<float>()) && bias.ndim() == 1 &&
                    bias.shape(0) == w[l + 1],
                "Actor: layer bias " + std::to_string(i / 2) + " must be a float32 (" +
                    std::to_string(w[l + 1]) + ",) array, got " + Shape(bias));
        pointers.push_back(static_cast<const float*>(weight.data()));
        pointers.push_back(static_cast<const float*>(bias.data()));
        keep_.push_back(weight);
        keep_.push_back(bias);
      }
    Require(i == layers.size(), "Actor: expected " + std::to_string(i) +
                                    " weight and bias arrays, got " +
                                    std::to_string(layers.size()));
    actor_ = std::make_unique<ftc::learn::Actor>(shape_, std::move(pointers));
  }

  py::tuple Forward(const Array<float>& obs) {
    Require(obs.ndim() == 2 && obs.shape(1) == shape_.trunk.front(),
            "Actor.forward: obs must be (N, " + std::to_string(shape_.trunk.front()) +
                "), got " + Shape(obs));
    const auto rows = static_cast<int>(obs.shape(0));
    const int out = shape_.policy.back();
    Array<float> logits({rows, out}), probs({rows, out}), values(rows);
    actor_->Forward(obs.data(), rows, logits.mutable_data(), probs.mutable_data(),
                    values.mutable_data());
    return py::make_tuple(logits, probs, values);
  }

 private:
  ftc::learn::ActorCriticShape shape_;
  std::vector<py::array> keep_;
  std::unique_ptr<ftc::learn::Actor> actor_;
};

Array<float> LogProb(const Array<float>& logits, const Array<float>& actions) {
  Require(logits.ndim() == 2 && actions.ndim() == 2 && logits.shape(0) == actions.shape(0) &&
              logits.shape(1) == actions.shape(1),
          "log_prob: logits and actions must be (N, K) alike, got " + Shape(logits) + " and " +
              Shape(actions));
  const auto rows = static_cast<int>(logits.shape(0)), cols = static_cast<int>(logits.shape(1));
  Array<float> out(rows);
  ftc::learn::BernoulliLogProb(logits.data(), actions.data(), rows, cols, out.mutable_data());
  return out;
}

}  // namespace

PYBIND11_MODULE(_learn, m) {
  m.doc() = "Learning kernels in C++ (cpp/learning): behaviour cloning, PPO epochs, acting.";
  m.def("distill", &Distill, py::arg("params"), py::arg("trunk"), py::arg("head"), py::arg("x"),
        py::arg("y"), py::arg("weights"), py::arg("orders"), py::arg("minibatch"),
        py::arg("lr"), py::arg("max_grad_norm"), py::arg("stop_loss") = 0.0,
        "Fit the logits of head(trunk(2 x - 1)) to 0/1 labels y by binary cross-entropy "
        "(the mean over a minibatch's rows, weighted by weights if not None, of the mean "
        "over columns), the global gradient-norm clip and a fresh Adam (eps 1e-5), one "
        "epoch per row of orders (a permutation of range(N)), stopping after an epoch "
        "whose mean minibatch loss is below stop_loss. params: float32, the trunk's then "
        "the head's layers, each W (in, out) row-major then b; updated in place. "
        "Returns (last minibatch loss, epochs run, Adam steps).");
  m.def("ppo_epoch", &PpoEpoch, py::arg("params"), py::arg("adam_m"), py::arg("adam_v"),
        py::arg("adam_t"), py::arg("trunk"), py::arg("policy"), py::arg("value"), py::arg("obs"),
        py::arg("actions"), py::arg("old_logprobs"), py::arg("advantages"), py::arg("returns"),
        py::arg("order"), py::kw_only(), py::arg("minibatch"), py::arg("clip_coef"),
        py::arg("ent_coef"), py::arg("vf_coef"), py::arg("max_grad_norm"), py::arg("norm_adv"),
        py::arg("lr"), py::arg("beta1"), py::arg("beta2"), py::arg("eps"),
        "One epoch of PPO (clipped surrogate, entropy bonus, value loss, global norm clip, "
        "Adam) over the rows in order, minibatch by minibatch, on the actor-critic whose "
        "parameters params holds (trunk, policy head, value head; each W (in, out) "
        "row-major then b). params, adam_m, adam_v (float32) are updated in place; adam_t "
        "is Adam's step count before the epoch. Returns (approx_kl per minibatch, clipfrac "
        "per minibatch, last policy loss, last value loss, Adam's step count after).");
  py::class_<PyActor>(m, "Actor", "The actor-critic's forward pass for acting, reading the "
                                  "weights where torch keeps them.")
      .def(py::init<const std::vector<int>&, const std::vector<int>&, const std::vector<int>&,
                    const py::list&>(),
           py::arg("trunk"), py::arg("policy"), py::arg("value"), py::arg("layers"),
           "layers: each Linear's weight (out, in) and bias as float32 arrays sharing "
           "torch's memory, trunk then policy head then value head; kept alive.")
      .def("forward", &PyActor::Forward, py::arg("obs"),
           "(logits (N, K), sigmoid(logits) (N, K), values (N,)) for obs (N, trunk[0]).");
  m.def("log_prob", &LogProb, py::arg("logits"), py::arg("actions"),
        "Sum over columns of the Bernoulli(sigmoid(logit)) log-probability of 0/1 actions.");
}
