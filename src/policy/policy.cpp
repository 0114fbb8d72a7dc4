#include "policy/policy.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>

namespace tether::policy {

namespace fs = std::filesystem;

std::unique_ptr<Policy> Policy::load(const std::string& checkpoint_dir, const models::LoadOptions& options) {
  if (!fs::is_directory(checkpoint_dir))
    throw Error(ErrorCode::not_found, checkpoint_dir + ": not a checkpoint directory");
  const std::string config_path = (fs::path(checkpoint_dir) / "config.json").string();
  if (!fs::exists(config_path)) throw Error(ErrorCode::not_found, config_path + ": missing (not a LeRobot checkpoint?)");
  const Json config = read_json_file(config_path);
  auto p = std::unique_ptr<Policy>(new Policy());
  p->dir_ = checkpoint_dir;
  p->model_ = models::load_model(checkpoint_dir, config, options);
  std::vector<std::string> post_warnings;
  p->pre_ = Normalizer::load(checkpoint_dir, "policy_preprocessor.json", "normalizer_processor", config, p->warnings_);
  p->post_ = Normalizer::load(checkpoint_dir, "policy_postprocessor.json", "unnormalizer_processor", config,
                              post_warnings);
  // The pre- and post-processor usually carry the same stats; report each missing feature once.
  for (const auto& w : post_warnings)
    if (std::find(p->warnings_.begin(), p->warnings_.end(), w) == p->warnings_.end()) p->warnings_.push_back(w);
  return p;
}

Observation synthetic_observation(const models::ModelSpec& spec) {
  Observation obs;
  for (const auto& camera : spec.cameras) {
    if (camera.find("empty_camera_") != std::string::npos) continue;  // the config's synthetic fillers
    vision::Image img;
    img.height = spec.image_height > 0 ? int(spec.image_height) : 224;
    img.width = spec.image_width > 0 ? int(spec.image_width) : 224;
    img.rgb.assign(std::size_t(img.height) * std::size_t(img.width) * 3, 128);
    obs.images[camera] = std::move(img);
  }
  obs.state.assign(std::size_t(spec.state_dim), 0.0f);
  obs.instruction = "warm up";
  return obs;
}

Prediction Policy::predict(const std::vector<Observation>& batch) {
  const auto t0 = std::chrono::steady_clock::now();
  const auto& s = spec();
  std::vector<models::ModelInput> inputs(batch.size());
  for (std::size_t b = 0; b < batch.size(); ++b) {
    const Observation& o = batch[b];
    if (int64_t(o.state.size()) != s.state_dim)
      throw Error(ErrorCode::invalid_argument, "state has " + std::to_string(o.state.size()) +
                                                   " values, the model expects " + std::to_string(s.state_dim));
    for (float v : o.state)
      if (!std::isfinite(v)) throw Error(ErrorCode::invalid_argument, "state contains NaN or Inf");
    for (const auto& [camera, image] : o.images) {
      if (std::find(s.cameras.begin(), s.cameras.end(), camera) == s.cameras.end()) {
        std::string known;
        for (const auto& c : s.cameras) known += (known.empty() ? "" : ", ") + c;
        throw Error(ErrorCode::invalid_argument, "unknown camera '" + camera + "' (the model knows: " + known + ")");
      }
    }
    models::ModelInput& in = inputs[b];
    in.images = o.images;
    in.state = o.state;
    pre_.normalize(s.state_key, in.state.data(), int64_t(in.state.size()));
    in.instruction = o.instruction;
    in.noise = o.noise;
    in.seed = o.seed;
  }
  Prediction out;
  out.normalize_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();

  models::ModelOutput m = model_->predict(inputs);
  out.timings = m.timings;

  if (debug_)
    debug_("out.actions_normalized", Tensor{DType::f32, {m.batch, m.chunk_size, m.action_dim}, m.actions.data(), nullptr});
  const auto t1 = std::chrono::steady_clock::now();
  const int64_t per_item = m.chunk_size * m.action_dim;
  for (int64_t b = 0; b < m.batch; ++b) {
    ActionChunk chunk;
    chunk.chunk_size = m.chunk_size;
    chunk.action_dim = m.action_dim;
    chunk.actions.assign(m.actions.begin() + b * per_item, m.actions.begin() + (b + 1) * per_item);
    post_.unnormalize(s.action_key, chunk.actions.data(), per_item);
    chunk.warnings = m.warnings[b];
    out.items.push_back(std::move(chunk));
  }
  const auto t2 = std::chrono::steady_clock::now();
  out.postprocess_ms = std::chrono::duration<double, std::milli>(t2 - t1).count();
  out.total_ms = std::chrono::duration<double, std::milli>(t2 - t0).count();
  return out;
}

}  // namespace tether::policy
