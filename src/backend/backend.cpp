// The registry of compiled backends: a CUDA backend adds its line here when nvcc builds it.
#include "backend/backend.h"

#include "backend/cpu/cpu_backend.h"
#include "core/error.h"

namespace tether::backend {

const char* device_name(Device d) { return d == Device::cpu ? "cpu" : "cuda"; }

const char* activation_name(Activation a) {
  switch (a) {
    case Activation::silu: return "silu";
    case Activation::gelu_tanh: return "gelu_tanh";
    case Activation::gelu_erf: return "gelu_erf";
    case Activation::relu: return "relu";
  }
  return "?";
}

namespace {
struct Entry {
  const char* name;
  std::shared_ptr<Backend> (*make)();
};
constexpr Entry kBackends[] = {
    {"cpu", &make_cpu_backend},
};
}  // namespace

std::vector<std::string> compiled_backends() {
  std::vector<std::string> out;
  for (const auto& e : kBackends) out.push_back(e.name);
  return out;
}

std::shared_ptr<Backend> make_backend(const std::string& name) {
  for (const auto& e : kBackends)
    if (name == e.name) return e.make();
  std::string known;
  for (const auto& e : kBackends) known += std::string(known.empty() ? "" : ", ") + e.name;
  throw Error(ErrorCode::invalid_argument, "backend '" + name + "' is not compiled in (compiled: " + known + ")");
}

}  // namespace tether::backend
