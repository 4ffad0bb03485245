// Python bindings of the learning kernels (module ftc._learn): arrays in,
// shapes checked here with messages that name the argument.
#include <pybind11/numpy.h>
#include <pybind11/pybind11.h>
#include <pybind11/stl.h>

#include <string>
#include <vector>

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

}  // namespace

PYBIND11_MODULE(_learn, m) {
  m.doc() = "Learning kernels in C++ (cpp/learning): behaviour cloning of the policy.";
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
}
