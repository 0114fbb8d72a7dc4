// SigLIP vision towers and the pixel-shuffle connector (see vision_tower.h).
#include "models/blocks/vision_tower.h"

#include <algorithm>
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

VisionConfig VisionConfig::from_siglip2_json(const Json& j, const std::string& where) {
  VisionConfig c = from_json(j, where);
  c.patch = json_get_or<int64_t>(j, "patch_size", 16, where);
  const int64_t n = json_get_or<int64_t>(j, "num_patches", 256, where);
  c.table_side = int64_t(std::lround(std::sqrt(double(n))));
  if (c.table_side * c.table_side != n)
    throw Error(ErrorCode::format, where + ": num_patches " + std::to_string(n) + " is not a square");
  c.position_ids = PositionIds::resized;
  c.linear_patch_embedding = true;
  c.image_size = c.table_side * c.patch;
  return c;
}

std::vector<float> resize_table_bilinear_aa(const float* table, int64_t side, int64_t d, int64_t out_h, int64_t out_w) {
  // One axis: per output index the first source index, the count and the normalised triangle weights (float32, in
  // torch's _compute_weights_aa order).
  struct Axis {
    std::vector<int64_t> start, count;
    std::vector<float> w;
    int64_t taps = 0;
  };
  auto axis = [](int64_t in, int64_t out) {
    Axis a;
    const float scale = float(in) / float(out);
    const float support = scale >= 1.0f ? scale : 1.0f;
    const float invscale = scale >= 1.0f ? 1.0f / scale : 1.0f;
    a.taps = int64_t(std::ceil(support)) * 2 + 1;
    a.start.resize(std::size_t(out));
    a.count.resize(std::size_t(out));
    a.w.assign(std::size_t(out * a.taps), 0.0f);
    for (int64_t i = 0; i < out; ++i) {
      const float center = scale * (float(i) + 0.5f);
      const int64_t xmin = std::max(int64_t(center - support + 0.5f), int64_t(0));
      const int64_t xsize = std::min(std::min(int64_t(center + support + 0.5f), in) - xmin, a.taps);
      float* w = &a.w[std::size_t(i * a.taps)];
      float total = 0.0f;
      for (int64_t j = 0; j < xsize; ++j) {
        float x = (float(j + xmin) - center + 0.5f) * invscale;
        x = x < 0 ? -x : x;
        w[j] = x < 1.0f ? 1.0f - x : 0.0f;
        total += w[j];
      }
      if (total != 0.0f)
        for (int64_t j = 0; j < xsize; ++j) w[j] /= total;
      a.start[std::size_t(i)] = xmin;
      a.count[std::size_t(i)] = xsize;
    }
    return a;
  };
  const Axis ax = axis(side, out_w), ay = axis(side, out_h);
  auto sample = [](const Axis& a, int64_t i, auto&& at) {
    const float* w = &a.w[std::size_t(i * a.taps)];
    float out = at(a.start[std::size_t(i)]) * w[0];
    for (int64_t j = 1; j < a.count[std::size_t(i)]; ++j) out += at(a.start[std::size_t(i)] + j) * w[j];
    return out;
  };
  // Width first (side x out_w), then height (out_h x out_w); a pass whose size does not change is skipped.
  std::vector<float> mid(std::size_t(side * out_w * d));
  for (int64_t y = 0; y < side; ++y)
    for (int64_t x = 0; x < out_w; ++x)
      for (int64_t c = 0; c < d; ++c)
        mid[std::size_t((y * out_w + x) * d + c)] =
            out_w == side ? table[(y * side + x) * d + c]
                          : sample(ax, x, [&](int64_t sx) { return table[(y * side + sx) * d + c]; });
  std::vector<float> out(std::size_t(out_h * out_w * d));
  for (int64_t y = 0; y < out_h; ++y)
    for (int64_t x = 0; x < out_w; ++x)
      for (int64_t c = 0; c < d; ++c)
        out[std::size_t((y * out_w + x) * d + c)] =
            out_h == side ? mid[std::size_t((y * out_w + x) * d + c)]
                          : sample(ay, y, [&](int64_t sy) { return mid[std::size_t((sy * out_w + x) * d + c)]; });
  return out;
}

void VisionTower::load(backend::Backend& be, Weights& w, const std::string& prefix, const VisionConfig& cfg,
                       cpu::Precision precision) {
  cfg_ = cfg;
  const int64_t d = cfg.hidden, f = cfg.intermediate, p = cfg.patch;
  const int64_t side = cfg.image_size / p, C = cfg.channels;
  if (cfg.linear_patch_embedding) {
    // [d, (row, column, channel)] -> the conv layout [d, channel, row, column] the backend's patch_embed reads.
    const float* lin = w.f32(prefix + "embeddings.patch_embedding.weight", {d, p * p * C});
    std::vector<float> conv(std::size_t(d * C * p * p));
    for (int64_t o = 0; o < d; ++o)
      for (int64_t y = 0; y < p; ++y)
        for (int64_t x = 0; x < p; ++x)
          for (int64_t c = 0; c < C; ++c)
            conv[std::size_t(((o * C + c) * p + y) * p + x)] = lin[o * p * p * C + (y * p + x) * C + c];
    patch_w_ = be.alloc<float>(int64_t(conv.size()));  // a copy: constant() would only view this local buffer
    be.upload(conv.data(), int64_t(conv.size()), patch_w_.at());
  } else {
    patch_w_ = be.constant(w.f32(prefix + "embeddings.patch_embedding.weight", {d, C, p, p}), d * C * p * p);
  }
  patch_b_ = be.constant(w.f32(prefix + "embeddings.patch_embedding.bias", {d}), d);
  if (cfg.position_ids == VisionConfig::PositionIds::resized) {
    const float* t = w.f32(prefix + "embeddings.position_embedding.weight", {side * side, d});
    pos_table_.assign(t, t + side * side * d);
  } else {
    pos_emb_ = be.table(w.raw(prefix + "embeddings.position_embedding.weight", {side * side, d}));
  }
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
  const bool resized = cfg_.position_ids == VisionConfig::PositionIds::resized;
  if (!resized && (height > cfg_.image_size || width > cfg_.image_size))
    throw Error(ErrorCode::invalid_argument, "vision tower: image larger than the position table allows");
  auto grow = [&](backend::Array<float>& a, int64_t size) {
    if (a.size() < size) a = be.alloc<float>(size);
  };
  grow(x_, m * d);
  grow(normed_, m * d);
  grow(qkv_, m * 3 * d);
  grow(attn_, m * d);
  grow(mlp_, m * f);
  if (resized && (pos_for_h_ != height || pos_for_w_ != width)) {
    const std::vector<float> rows =
        resize_table_bilinear_aa(pos_table_.data(), cfg_.table_side, d, height / cfg_.patch, width / cfg_.patch);
    pos_rows_ = be.alloc<float>(n * d);
    be.upload(rows.data(), n * d, pos_rows_.at());
    pos_for_h_ = height;
    pos_for_w_ = width;
  } else if (pos_for_h_ != height || pos_for_w_ != width) {
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
