// The parts of predict() that every flow-matching family shares (Model::begin_predict, Model::sample_actions).
#include "models/model.h"

#include <algorithm>
#include <chrono>
#include <cstring>

#include "core/error.h"

namespace tether::models {

ModelOutput Model::begin_predict(const std::vector<ModelInput>& batch) const {
  if (batch.empty()) throw Error(ErrorCode::invalid_argument, "predict: empty batch");
  const ModelSpec& s = spec();
  const int64_t C = s.noise_rows(), A = s.max_action_dim;
  for (std::size_t b = 0; b < batch.size(); ++b) {
    if (int64_t(batch[b].state.size()) != s.state_dim)
      throw Error(ErrorCode::invalid_argument, "observation " + std::to_string(b) + ": state has " +
                                                   std::to_string(batch[b].state.size()) + " values, the model expects " +
                                                   std::to_string(s.state_dim));
    if (!batch[b].noise.empty() && int64_t(batch[b].noise.size()) != C * A)
      throw Error(ErrorCode::invalid_argument, "observation " + std::to_string(b) + ": noise has " +
                                                   std::to_string(batch[b].noise.size()) + " values, expected " +
                                                   std::to_string(C) + "x" + std::to_string(A));
  }
  ModelOutput out;
  out.batch = int64_t(batch.size());
  out.chunk_size = s.chunk_size;
  out.action_dim = s.action_dim;
  out.warnings.resize(batch.size());
  return out;
}

void Model::sample_actions(backend::Backend& be, const std::vector<ModelInput>& batch, backend::Ptr<float> x,
                           backend::Ptr<float> v, const Schedule& schedule, const VelocityFn& velocity,
                           const std::function<void(backend::Ptr<const float> v)>& on_step0_velocity,
                           ModelOutput& out) const {
  const ModelSpec& s = spec();
  const auto t0 = std::chrono::steady_clock::now();
  const int64_t B = int64_t(batch.size()), C = s.noise_rows(), A = s.max_action_dim;
  std::vector<float> noise(std::size_t(B * C * A));
  for (int64_t b = 0; b < B; ++b) {
    float* dst = &noise[std::size_t(b * C * A)];
    if (batch[b].noise.empty()) seeded_normal(batch[b].seed, dst, C * A);
    else std::copy(batch[b].noise.begin(), batch[b].noise.end(), dst);
  }
  be.upload(noise.data(), B * C * A, x);
  std::vector<DenoiseControl> controls;
  controls.reserve(batch.size());
  for (const auto& item : batch) controls.push_back(item.denoise);
  out.steps_used = euler_sample(be, x, v, {B, C, A, s.action_dim}, schedule, controls, velocity, on_step0_velocity);
  be.synchronize();  // a GPU runs behind the host: time the work, not its queueing
  out.timings.set("denoise", std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count());

  // `noise` is reused for the result: the padded [B*C, A] rows, then cut to the first chunk_size rows of each item
  // and to action_dim.
  be.download(backend::Ptr<const float>(x), B * C * A, noise.data());
  const int64_t kept = s.chunk_size;
  out.actions.resize(std::size_t(B * kept * s.action_dim));
  for (int64_t b = 0; b < B; ++b)
    for (int64_t r = 0; r < kept; ++r)
      std::memcpy(&out.actions[std::size_t((b * kept + r) * s.action_dim)], &noise[std::size_t((b * C + r) * A)],
                  std::size_t(s.action_dim) * sizeof(float));
}

void Model::dump_prefix_kv(backend::Backend& be, const std::vector<backend::Array<float>>& k,
                           const std::vector<backend::Array<float>>& v, int64_t capacity, int64_t B, int64_t Lp,
                           int64_t kv_heads, int64_t head_dim) const {
  if (!debug_ || k.empty()) return;
  const int64_t kv_dim = kv_heads * head_dim;
  for (std::size_t layer : {std::size_t(0), k.size() - 1}) {
    for (const bool is_k : {true, false}) {
      const auto& cache = is_k ? k[layer] : v[layer];
      std::vector<float> compact(std::size_t(B * Lp * kv_dim));
      for (int64_t b = 0; b < B; ++b)
        be.download(backend::Ptr<const float>(cache.at(b * capacity * kv_dim)), Lp * kv_dim,
                    &compact[std::size_t(b * Lp * kv_dim)]);
      debug_(std::string("mid.prefix_") + (is_k ? "k" : "v") + "." + std::to_string(layer),
             Tensor{DType::f32, {B, Lp, kv_heads, head_dim}, compact.data(), nullptr});
    }
  }
}

}  // namespace tether::models
