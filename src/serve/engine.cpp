// A Policy behind the Engine interface: the policy is shared by the predict closure, so it lives as long as the
// batcher that calls it.
#include "serve/engine.h"

#include <filesystem>

#include "backend/cpu/gemm.h"
#include "core/hash.h"

namespace tether::serve {

Engine load_policy_engine(const std::string& checkpoint_dir, const models::LoadOptions& options) {
  std::shared_ptr<policy::Policy> p = policy::Policy::load(checkpoint_dir, options);
  Engine e;
  e.spec = p->spec();
  e.load_warnings = p->load_warnings();
  e.normalization = p->input_normalizer().describe();
  e.gemm = cpu::blas_name();
  e.precision = cpu::precision_name(p->spec().precision);
  const auto weights = std::filesystem::path(checkpoint_dir) / "model.safetensors";
  e.model_hash = "sha256:" + sha256_file_hex(weights.string());
  e.predict = [p](const std::vector<policy::Observation>& batch) { return p->predict(batch); };
  return e;
}

}  // namespace tether::serve
