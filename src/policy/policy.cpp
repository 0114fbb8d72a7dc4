// Policy: load a checkpoint through its family, normalise, predict, unnormalise (see policy.h).
#include "policy/policy.h"

#include <algorithm>
#include <chrono>
#include <cmath>

#include "text/unicode.h"

namespace tether::policy {

namespace {

// The model-side denoise control of one observation. RTC's leftover goes back to the model's normalised space (the
// inverse of the output unnormalisation), then either zero-padded to [chunk, max_action_dim] with the RTC prefix
// weights (guidance; execution horizon capped to the leftover length, as upstream does) or made the start of the
// sampler's first rows (inpainting, GR00T).
models::DenoiseControl denoise_control(const Observation& o, const models::ModelSpec& s, const Normalizer& post) {
  auto fail = [](const std::string& message) { throw Error(ErrorCode::invalid_argument, message); };
  models::DenoiseControl c;
  if (!std::isfinite(o.adaptive_threshold) || o.adaptive_threshold < 0)
    fail("adaptive_threshold must be a finite number >= 0, got " + std::to_string(o.adaptive_threshold));
  c.adaptive_threshold = o.adaptive_threshold;
  if (!o.rtc) return c;
  if (s.rtc_refused_for_relative())
    fail("rtc: this policy predicts actions relative to the state, so a previous chunk's leftover does not "
         "carry over; real-time chunking is off for it");
  const Observation::Rtc& r = *o.rtc;
  const int64_t A = s.action_dim, C = s.chunk_size, values = int64_t(r.prev_actions.size());
  const int64_t n = values / A;
  if (values == 0 || values % A != 0 || n > C)
    fail("rtc.prev_actions has " + std::to_string(values) + " values; expected n x " + std::to_string(A) +
         " (n rows of action_dim values, 1 <= n <= chunk_size " + std::to_string(C) + ")");
  for (float v : r.prev_actions)
    if (!std::isfinite(v)) fail("rtc.prev_actions contains NaN or Inf");
  if (r.inference_delay < 0 || r.inference_delay >= C)
    fail("rtc.inference_delay must be in [0, " + std::to_string(C) + "), got " + std::to_string(r.inference_delay));
  if (r.execution_horizon < 1)
    fail("rtc.execution_horizon must be >= 1, got " + std::to_string(r.execution_horizon));
  if (!std::isfinite(r.max_guidance_weight) || r.max_guidance_weight <= 0)
    fail("rtc.max_guidance_weight must be a finite number > 0, got " + std::to_string(r.max_guidance_weight));

  std::vector<float> prev = r.prev_actions;
  // Relative actions: the leftover, absolute against the state it was predicted from, is made relative to this
  // request's state first (lerobot's reanchor_relative_rtc_prefix; the robot has moved since).
  if (s.relative_actions) post.to_relative(prev.data(), n, A, o.state);
  post.invert_unnormalize(s.action_key, prev.data(), values);
  if (s.rtc == models::RtcMethod::inpainting) {
    models::inpainting_rtc(prev, A, s.max_action_dim, s.noise_rows(), r.execution_horizon, r.inference_delay,
                           s.rtc_ramp_rate, c);
    return c;
  }
  c.rtc_target.assign(std::size_t(C * s.max_action_dim), 0.0f);
  for (int64_t i = 0; i < n; ++i)
    std::copy_n(&prev[std::size_t(i * A)], A, &c.rtc_target[std::size_t(i * s.max_action_dim)]);
  c.rtc_weights = models::rtc_prefix_weights(r.inference_delay, int(std::min<int64_t>(r.execution_horizon, n)), int(C),
                                             r.schedule);
  c.rtc_max_guidance_weight = r.max_guidance_weight;
  return c;
}

}  // namespace

std::unique_ptr<Policy> Policy::load(const std::string& checkpoint_dir, const models::LoadOptions& options) {
  models::LoadedCheckpoint c = models::load_checkpoint(checkpoint_dir, options);
  auto p = std::unique_ptr<Policy>(new Policy());
  p->dir_ = checkpoint_dir;
  p->family_ = c.family;
  p->weight_files_ = std::move(c.weight_files);
  p->model_ = std::move(c.model);
  p->pre_ = Normalizer(std::move(c.normalization.input));
  p->post_ = Normalizer(std::move(c.normalization.output));
  p->warnings_ = std::move(c.normalization.warnings);
  return p;
}

Observation synthetic_observation(const models::ModelSpec& spec) {
  Observation obs;
  for (const auto& camera : spec.cameras) {
    if (std::find(spec.synthetic_cameras.begin(), spec.synthetic_cameras.end(), camera) != spec.synthetic_cameras.end())
      continue;  // the model fills these itself
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
    // Checked here, before any item of the batch reaches the model. The tokenizer would refuse it too, but with a
    // message naming its own file and an offset into the prompt the family built around the instruction.
    if (const std::size_t bad = text::find_invalid_utf8(o.instruction); bad != std::string::npos)
      throw Error(ErrorCode::invalid_argument,
                  "instruction is not valid UTF-8 (byte " + std::to_string(bad) + " of " +
                      std::to_string(o.instruction.size()) + ")");
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
    in.denoise = denoise_control(o, s, post_);
  }
  Prediction out;
  out.normalize_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();

  models::ModelOutput m = model_->predict(inputs);
  out.timings = m.timings;
  out.flops = m.flops;

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
    post_.to_absolute(chunk.actions.data(), m.chunk_size, m.action_dim, batch[std::size_t(b)].state);
    chunk.warnings = m.warnings[b];
    chunk.denoise_steps_used = m.steps_used.empty() ? 0 : m.steps_used[b];
    out.items.push_back(std::move(chunk));
  }
  const auto t2 = std::chrono::steady_clock::now();
  out.postprocess_ms = std::chrono::duration<double, std::milli>(t2 - t1).count();
  out.total_ms = std::chrono::duration<double, std::milli>(t2 - t0).count();
  return out;
}

}  // namespace tether::policy
