// The registry of compiled backends: a CUDA backend adds its line here when nvcc builds it.
#include "backend/backend.h"

#include <cstdlib>

#include "backend/cpu/cpu_backend.h"
#include "core/error.h"
#if TETHER_HAVE_CUDA
#include "backend/cuda/cuda_backend.h"
#endif

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
bool cpu_usable(std::string*) { return true; }

struct Entry {
  const char* name;
  std::shared_ptr<Backend> (*make)();
  bool (*usable)(std::string* why);
};
// In the order "auto" tries them.
constexpr Entry kBackends[] = {
#if TETHER_HAVE_CUDA
    {"cuda", &make_cuda_backend, &cuda_usable},
#endif
    {"cpu", &make_cpu_backend, &cpu_usable},
};

std::string known_names() {
  std::string known;
  for (const auto& e : kBackends) known += std::string(known.empty() ? "" : ", ") + e.name;
  return known;
}
}  // namespace

std::vector<std::string> compiled_backends() {
  std::vector<std::string> out;
  for (const auto& e : kBackends) out.push_back(e.name);
  return out;
}

bool backend_usable(const std::string& name, std::string* why) {
  const std::string chosen = resolve_backend(name);
  for (const auto& e : kBackends)
    if (chosen == e.name) return e.usable(why);
  if (why)
    *why = chosen == "cuda" ? "backend 'cuda' is not compiled into this build (CMake found no nvcc; compiled: " +
                                  known_names() + ")"
                            : "backend '" + chosen + "' is not compiled in (compiled: " + known_names() + ")";
  return false;
}

std::string resolve_backend(const std::string& name) {
  if (name != "auto") return name;
  for (const auto& e : kBackends)
    if (e.usable(nullptr)) return e.name;
  return "cpu";
}

std::shared_ptr<Backend> make_backend(const std::string& name) {
  const std::string chosen = resolve_backend(name);
  for (const auto& e : kBackends)
    if (chosen == e.name) return e.make();
  std::string why;
  backend_usable(chosen, &why);
  throw Error(ErrorCode::invalid_argument, why);
}

std::shared_ptr<Backend> make_default_backend() {
  const char* chosen = std::getenv("TETHER_BACKEND");
  return make_backend(chosen && *chosen ? chosen : "cpu");
}

}  // namespace tether::backend
