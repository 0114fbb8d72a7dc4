// A Policy behind the Engine interface: the policy is shared by the predict closure, so it lives as long as the
// batcher that calls it.
#include "serve/engine.h"

#include <filesystem>

#include "backend/cpu/gemm.h"
#include "core/hash.h"

namespace tether::serve {

Engine load_policy_engine(const std::string& checkpoint_dir) {
  std::shared_ptr<policy::Policy> p = policy::Policy::load(checkpoint_dir);
  Engine e;
  e.spec = p->spec();
  e.load_warnings = p->load_warnings();
  e.normalization = p->input_normalizer().describe();
  e.gemm = cpu::blas_name();
  const auto weights = std::filesystem::path(checkpoint_dir) / "model.safetensors";
  e.model_hash = "sha256:" + sha256_file_hex(weights.string());
  e.predict = [p](const std::vector<policy::Observation>& batch) { return p->predict(batch); };
  return e;
}

policy::Observation synthetic_observation(const models::ModelSpec& spec) {
  policy::Observation obs;
  for (const auto& camera : spec.cameras) {
    if (camera.find("empty_camera_") != std::string::npos) continue;
    vision::Image img;
    img.height = spec.image_height > 0 ? int(spec.image_height) : 224;
    img.width = spec.image_width > 0 ? int(spec.image_width) : 224;
    img.rgb.assign(std::size_t(img.height) * img.width * 3, 128);
    obs.images[camera] = std::move(img);
  }
  obs.state.assign(std::size_t(spec.state_dim), 0.0f);
  obs.instruction = "warm up";
  return obs;
}

}  // namespace tether::serve
