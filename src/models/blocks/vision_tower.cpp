// SigLIP vision towers and the pixel-shuffle connector (see vision_tower.h).
#include "models/blocks/vision_tower.h"

#include <cmath>

#include "models/blocks/linear.h"

namespace tether::models {

using backend::Ptr;

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

void VisionTower::load(backend::Backend& be, Weights& w, const std::string& prefix, const VisionConfig& cfg,
                       cpu::Precision precision) {
  cfg_ = cfg;
  const int64_t d = cfg.hidden, f = cfg.intermediate, p = cfg.patch;
  const int64_t side = cfg.image_size / p;
  patch_w_ = be.constant(w.f32(prefix + "embeddings.patch_embedding.weight", {d, cfg.channels, p, p}),
                         d * cfg.channels * p * p);
  patch_b_ = be.constant(w.f32(prefix + "embeddings.patch_embedding.bias", {d}), d);
  pos_emb_ = be.table(w.raw(prefix + "embeddings.position_embedding.weight", {side * side, d}));
  if (cfg.post_norm) {
    post_ln_w_ = be.constant(w.f32(prefix + "post_layernorm.weight", {d}), d);
    post_ln_b_ = be.constant(w.f32(prefix + "post_layernorm.bias", {d}), d);
  }
  layers_.resize(std::size_t(cfg.layers));
  for (int64_t i = 0; i < cfg.layers; ++i) {
    const std::string lp = prefix + "encoder.layers." + std::to_string(i) + ".";
    Layer& L = layers_[i];
    L.ln1_w = be.constant(w.f32(lp + "layer_norm1.weight", {d}), d);
    L.ln1_b = be.constant(w.f32(lp + "layer_norm1.bias", {d}), d);
    L.ln2_w = be.constant(w.f32(lp + "layer_norm2.weight", {d}), d);
    L.ln2_b = be.constant(w.f32(lp + "layer_norm2.bias", {d}), d);
    L.qkv = load_stacked_linear(be, w, {{lp + "self_attn.q_proj", d}, {lp + "self_attn.k_proj", d}, {lp + "self_attn.v_proj", d}},
                                d, true, precision);
    L.o = load_linear(be, w, lp + "self_attn.out_proj", d, d, true, precision);
    L.fc1 = load_linear(be, w, lp + "mlp.fc1", f, d, true, precision);
    L.fc2 = load_linear(be, w, lp + "mlp.fc2", d, f, true, precision);
  }
}

// Patch position ids. Bucketed: fractional patch coordinates bucketised against boundaries k / side in float32, as
// the Idefics3 embedding computes them for an unmasked image. Sequential: row-major 0..n-1 on the native grid.
void VisionTower::position_ids(int64_t patches_h, int64_t patches_w, std::vector<int64_t>& ids) const {
  const int64_t side = cfg_.image_size / cfg_.patch;
  ids.resize(std::size_t(patches_h * patches_w));
  if (cfg_.position_ids == VisionConfig::PositionIds::sequential) {
    if (patches_h != side || patches_w != side)
      throw Error(ErrorCode::invalid_argument, "vision tower: this tower takes " + std::to_string(cfg_.image_size) +
                                                   "x" + std::to_string(cfg_.image_size) + " images only");
    for (int64_t i = 0; i < patches_h * patches_w; ++i) ids[i] = i;
    return;
  }
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
  for (int64_t r = 0; r < patches_h; ++r)
    for (int64_t c = 0; c < patches_w; ++c) ids[r * patches_w + c] = bucket(r, patches_h) * side + bucket(c, patches_w);
}

void VisionTower::forward(backend::Backend& be, Ptr<const float> pixels, int64_t batch, int64_t height, int64_t width,
                          Ptr<float> out) {
  const int64_t d = cfg_.hidden, f = cfg_.intermediate, heads = cfg_.heads, hd = d / heads;
  const int64_t n = num_patches(height, width), m = batch * n;
  if (height % cfg_.patch || width % cfg_.patch)
    throw Error(ErrorCode::invalid_argument, "vision tower: image " + std::to_string(height) + "x" +
                                                 std::to_string(width) + " is not a multiple of the patch size");
  if (height > cfg_.image_size || width > cfg_.image_size)
    throw Error(ErrorCode::invalid_argument, "vision tower: image larger than the position table allows");
  auto grow = [&](backend::Array<float>& a, int64_t size) {
    if (a.size() < size) a = be.alloc<float>(size);
  };
  grow(x_, m * d);
  grow(normed_, m * d);
  grow(qkv_, m * 3 * d);
  grow(attn_, m * d);
  grow(mlp_, m * f);
  if (pos_for_h_ != height || pos_for_w_ != width) {
    std::vector<int64_t> ids;
    position_ids(height / cfg_.patch, width / cfg_.patch, ids);
    pos_ids_ = be.alloc<int64_t>(n);
    be.upload(ids.data(), n, pos_ids_.at());
    pos_rows_ = be.alloc<float>(n * d);
    be.gather_rows(*pos_emb_, pos_ids_.at(), n, 1.0f, pos_rows_.at());
    pos_for_h_ = height;
    pos_for_w_ = width;
  }
  be.patch_embed(pixels, batch, cfg_.channels, height, width, patch_w_.at(), patch_b_.at(), d, cfg_.patch, x_.at());
  for (int64_t b = 0; b < batch; ++b) be.add(x_.at(b * n * d), pos_rows_.at(), n * d, x_.at(b * n * d));
  const float scale_qk = 1.0f / std::sqrt(float(hd));
  for (const Layer& L : layers_) {
    be.layer_norm(x_.at(), m, d, L.ln1_w.at(), L.ln1_b.at(), cfg_.layer_norm_eps, normed_.at());
    be.linear(*L.qkv, normed_.at(), m, qkv_.at());
    be.attention(qkv_.at(), 3 * d, qkv_.at(d), qkv_.at(2 * d), 3 * d, Ptr<const uint8_t>(), batch, n, n, heads, heads, hd,
                 scale_qk, attn_.at());
    be.linear(*L.o, attn_.at(), m, x_.at(), /*accumulate=*/true);
    be.layer_norm(x_.at(), m, d, L.ln2_w.at(), L.ln2_b.at(), cfg_.layer_norm_eps, normed_.at());
    be.linear(*L.fc1, normed_.at(), m, mlp_.at());
    be.activate(mlp_.at(), m * f, backend::Activation::gelu_tanh);
    be.linear(*L.fc2, mlp_.at(), m, x_.at(), /*accumulate=*/true);
  }
  if (cfg_.post_norm) be.layer_norm(x_.at(), m, d, post_ln_w_.at(), post_ln_b_.at(), cfg_.layer_norm_eps, out);
  else be.copy_rows(x_.at(), d, out, d, m, d);
}

double VisionTower::flops(int64_t batch, int64_t height, int64_t width) const {
  const int64_t n = num_patches(height, width), m = batch * n, d = cfg_.hidden;
  double total = 2.0 * double(m) * double(d) * double(cfg_.channels * cfg_.patch * cfg_.patch);  // patch embedding
  for (const Layer& L : layers_) {
    for (const auto* lin : {&L.qkv, &L.o, &L.fc1, &L.fc2}) total += linear_flops(**lin, m);
    total += 4.0 * double(batch) * double(n) * double(n) * double(d);  // scores and the weighted sum
  }
  return total;
}

void PixelShuffleConnector::load(backend::Backend& be, Weights& w, const std::string& prefix, int64_t vision_hidden,
                                 int64_t scale_factor, int64_t text_hidden, cpu::Precision precision) {
  vision_hidden_ = vision_hidden;
  scale_ = scale_factor;
  text_hidden_ = text_hidden;
  proj_ = load_linear(be, w, prefix + "modality_projection.proj", text_hidden, vision_hidden * scale_factor * scale_factor,
                      false, precision);
}

void PixelShuffleConnector::forward(backend::Backend& be, Ptr<const float> x, int64_t batch, int64_t patches,
                                    Ptr<float> out) {
  const int64_t side = int64_t(std::lround(std::sqrt(double(patches))));
  if (side * side != patches || side % scale_ != 0)
    throw Error(ErrorCode::invalid_argument, "connector: " + std::to_string(patches) +
                                                 " patches do not form a square divisible by the scale factor");
  const int64_t t = tokens(patches), k = vision_hidden_ * scale_ * scale_;
  if (shuffled_.size() < batch * t * k) shuffled_ = be.alloc<float>(batch * t * k);
  be.pixel_shuffle(x, batch, patches, vision_hidden_, scale_, shuffled_.at());
  be.linear(*proj_, shuffled_.at(), batch * t, out);
}

double PixelShuffleConnector::flops(int64_t batch, int64_t patches) const {
  return linear_flops(*proj_, batch * tokens(patches));
}

}  // namespace tether::models
