#include "models/siglip.h"

#include <cmath>
#include <cstring>

#include "backend/cpu/gemm.h"
#include "backend/cpu/kernels.h"

namespace tether::models {

using namespace tether::cpu;

VisionConfig VisionConfig::from_json(const Json& j, const std::string& where) {
  // Defaults are those of transformers' SmolVLMVisionConfig, which save_pretrained may omit.
  VisionConfig c;
  c.hidden = json_get_or<int64_t>(j, "hidden_size", 1152, where);
  c.intermediate = json_get_or<int64_t>(j, "intermediate_size", 3072, where);
  c.layers = json_get_or<int64_t>(j, "num_hidden_layers", 12, where);
  c.heads = json_get_or<int64_t>(j, "num_attention_heads", 16, where);
  c.channels = json_get_or<int64_t>(j, "num_channels", 3, where);
  c.image_size = json_get_or<int64_t>(j, "image_size", 224, where);
  c.patch = json_get_or<int64_t>(j, "patch_size", 32, where);
  c.layer_norm_eps = json_get_or<float>(j, "layer_norm_eps", 1e-6f, where);
  const std::string act = json_get_or<std::string>(j, "hidden_act", "gelu_pytorch_tanh", where);
  if (act != "gelu_pytorch_tanh")
    throw Error(ErrorCode::unsupported, where + ": vision hidden_act '" + act + "' (only gelu_pytorch_tanh)");
  if (c.hidden % c.heads != 0)
    throw Error(ErrorCode::format, where + ": vision hidden_size is not a multiple of num_attention_heads");
  return c;
}

void VisionTower::load(Weights& w, const std::string& prefix, const VisionConfig& cfg, cpu::Precision precision) {
  cfg_ = cfg;
  const int64_t d = cfg.hidden, f = cfg.intermediate, p = cfg.patch;
  const int64_t side = cfg.image_size / p;
  patch_w_ = w.f32(prefix + "embeddings.patch_embedding.weight", {d, cfg.channels, p, p});
  patch_b_ = w.f32(prefix + "embeddings.patch_embedding.bias", {d});
  pos_emb_ = w.f32(prefix + "embeddings.position_embedding.weight", {side * side, d});
  post_ln_w_ = w.f32(prefix + "post_layernorm.weight", {d});
  post_ln_b_ = w.f32(prefix + "post_layernorm.bias", {d});
  layers_.resize(std::size_t(cfg.layers));
  for (int64_t i = 0; i < cfg.layers; ++i) {
    const std::string lp = prefix + "encoder.layers." + std::to_string(i) + ".";
    Layer& L = layers_[i];
    L.ln1_w = w.f32(lp + "layer_norm1.weight", {d});
    L.ln1_b = w.f32(lp + "layer_norm1.bias", {d});
    L.ln2_w = w.f32(lp + "layer_norm2.weight", {d});
    L.ln2_b = w.f32(lp + "layer_norm2.bias", {d});
    const std::vector<float> qkv = w.stacked({{lp + "self_attn.q_proj.weight", {d, d}},
                                              {lp + "self_attn.k_proj.weight", {d, d}},
                                              {lp + "self_attn.v_proj.weight", {d, d}}});
    const std::vector<float> qkv_b = w.stacked({{lp + "self_attn.q_proj.bias", {d}},
                                                {lp + "self_attn.k_proj.bias", {d}},
                                                {lp + "self_attn.v_proj.bias", {d}}});
    L.qkv.pack(qkv.data(), 3 * d, d, qkv_b.data(), precision);
    pack_linear(w, L.o, lp + "self_attn.out_proj", d, d, true, precision);
    pack_linear(w, L.fc1, lp + "mlp.fc1", f, d, true, precision);
    pack_linear(w, L.fc2, lp + "mlp.fc2", d, f, true, precision);
  }
}

// Patch position ids the way the upstream embedding computes them for an unmasked image: fractional patch
// coordinates bucketised against boundaries k / side (float32 arithmetic, as upstream), which lets a
// smaller-than-native image reuse the native position table.
void VisionTower::position_ids(int64_t patches_h, int64_t patches_w, std::vector<int64_t>& ids) const {
  const int64_t side = cfg_.image_size / cfg_.patch;
  const double step = 1.0 / double(side);
  std::vector<float> boundaries;
  const int64_t n_bounds = int64_t(std::ceil((1.0 - step) / step));
  for (int64_t k = 0; k < n_bounds; ++k) boundaries.push_back(float(step + double(k) * step));
  auto bucket = [&](int64_t index, int64_t count) {
    float frac = float(index) * (1.0f / float(count));
    frac = std::min(frac, float(1.0 - 1e-6));
    int64_t b = 0;
    while (b < int64_t(boundaries.size()) && boundaries[b] <= frac) ++b;  // bucketize(right=True)
    return b;
  };
  ids.resize(std::size_t(patches_h * patches_w));
  for (int64_t r = 0; r < patches_h; ++r)
    for (int64_t c = 0; c < patches_w; ++c) ids[r * patches_w + c] = bucket(r, patches_h) * side + bucket(c, patches_w);
}

void VisionTower::forward(const float* pixels, int64_t batch, int64_t height, int64_t width, float* out) {
  const int64_t d = cfg_.hidden, f = cfg_.intermediate, heads = cfg_.heads, hd = d / heads;
  const int64_t n = num_patches(height, width), m = batch * n;
  if (height % cfg_.patch || width % cfg_.patch)
    throw Error(ErrorCode::invalid_argument, "vision tower: image " + std::to_string(height) + "x" +
                                                 std::to_string(width) + " is not a multiple of the patch size");
  if (height > cfg_.image_size || width > cfg_.image_size)
    throw Error(ErrorCode::invalid_argument, "vision tower: image larger than the position table allows");
  x_.resize(std::size_t(m * d));
  normed_.resize(std::size_t(m * d));
  qkv_.resize(std::size_t(m * 3 * d));
  attn_.resize(std::size_t(m * d));
  mlp_.resize(std::size_t(m * f));

  patch_embed(pixels, batch, cfg_.channels, height, width, patch_w_, patch_b_, d, cfg_.patch, x_.data());
  position_ids(height / cfg_.patch, width / cfg_.patch, pos_ids_);
  for (int64_t b = 0; b < batch; ++b)
    for (int64_t t = 0; t < n; ++t) add(&x_[(b * n + t) * d], pos_emb_ + pos_ids_[t] * d, d, &x_[(b * n + t) * d]);

  const float scale_qk = 1.0f / std::sqrt(float(hd));
  for (const Layer& L : layers_) {
    layer_norm(x_.data(), m, d, L.ln1_w, L.ln1_b, cfg_.layer_norm_eps, normed_.data());
    L.qkv.forward(normed_.data(), m, qkv_.data());
    attention(qkv_.data(), 3 * d, qkv_.data() + d, qkv_.data() + 2 * d, 3 * d, nullptr, batch, n, n, heads, heads, hd,
              scale_qk, attn_.data());
    L.o.forward(attn_.data(), m, x_.data(), /*accumulate=*/true);
    layer_norm(x_.data(), m, d, L.ln2_w, L.ln2_b, cfg_.layer_norm_eps, normed_.data());
    L.fc1.forward(normed_.data(), m, mlp_.data());
    gelu_tanh(mlp_.data(), m * f);
    L.fc2.forward(mlp_.data(), m, x_.data(), /*accumulate=*/true);
  }
  layer_norm(x_.data(), m, d, post_ln_w_, post_ln_b_, cfg_.layer_norm_eps, out);
}

void PixelShuffleConnector::load(Weights& w, const std::string& prefix, int64_t vision_hidden, int64_t scale_factor,
                                 int64_t text_hidden, cpu::Precision precision) {
  vision_hidden_ = vision_hidden;
  scale_ = scale_factor;
  text_hidden_ = text_hidden;
  pack_linear(w, proj_, prefix + "modality_projection.proj", text_hidden, vision_hidden * scale_factor * scale_factor,
              false, precision);
}

void PixelShuffleConnector::forward(const float* x, int64_t batch, int64_t patches, float* out) {
  const int64_t side = int64_t(std::lround(std::sqrt(double(patches))));
  if (side * side != patches || side % scale_ != 0)
    throw Error(ErrorCode::invalid_argument, "connector: " + std::to_string(patches) +
                                                 " patches do not form a square divisible by the scale factor");
  const int64_t t = tokens(patches), k = vision_hidden_ * scale_ * scale_;
  shuffled_.resize(std::size_t(batch * t * k));
  pixel_shuffle(x, batch, patches, vision_hidden_, scale_, shuffled_.data());
  proj_.forward(shuffled_.data(), batch * t, out);
}

}  // namespace tether::models
