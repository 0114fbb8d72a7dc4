// A Policy behind the Engine interface: the policy is shared by the predict closure, so it lives as long as the
// batcher that calls it.
#include "serve/engine.h"

#include <algorithm>
#include <filesystem>

#include "backend/cpu/packed_linear.h"

namespace tether::serve {

std::string checkpoint_name(const std::string& checkpoint_dir) {
  const auto path = std::filesystem::path(checkpoint_dir).lexically_normal();
  const std::string name = path.filename().string();
  return name.empty() ? path.parent_path().filename().string() : name;
}

Engine load_policy_engine(const std::string& checkpoint_dir, const models::LoadOptions& options) {
  std::shared_ptr<policy::Policy> p = policy::Policy::load(checkpoint_dir, options);
  Engine e;
  e.spec = p->spec();
  e.load_warnings = p->load_warnings();
  e.normalization = p->input_normalizer().describe();
  for (const auto& line : p->output_normalizer().describe())  // lerobot's pre-processor may list the action too
    if (std::find(e.normalization.begin(), e.normalization.end(), line) == e.normalization.end())
      e.normalization.push_back(line);
  e.backend = p->spec().backend;
  e.gemm = e.backend == "cpu" ? cpu::gemm_name(p->spec().precision) : "cublaslt";
  e.precision = cpu::precision_name(p->spec().precision);
  e.compute = e.backend == "cpu" ? cpu::compute_mode(p->spec().precision) : cpu::precision_name(p->spec().precision);
  e.model_hash = models::weights_hash(checkpoint_dir, p->weight_files());
  e.model_name = checkpoint_name(checkpoint_dir);
  const std::string state_key = p->spec().state_key;
  e.normalize_state = [p, state_key](const std::vector<float>& state) {
    std::vector<float> out = state;
    p->input_normalizer().normalize(state_key, out.data(), int64_t(out.size()));
    return out;
  };
  const auto& post = p->output_normalizer().features();
  const auto action = post.find(p->spec().action_key);
  // Trained on normalised actions but shipped without the stats to undo it (identity-mode actions are robot units).
  e.actions_normalized = action != post.end() && action->second.mode != policy::NormMode::identity &&
                         !action->second.has_stats;
  e.predict = [p](const std::vector<policy::Observation>& batch) { return p->predict(batch); };
  return e;
}

}  // namespace tether::serve
