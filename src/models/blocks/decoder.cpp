// Decoder layers and the cached-prefix decoder stack, against the backend interface.
#include "models/blocks/decoder.h"

#include <cmath>

#include "models/blocks/linear.h"

namespace tether::models {

using backend::Activation;
using backend::Ptr;

DecoderConfig DecoderConfig::from_llama_json(const Json& j, const std::string& where) {
  // Defaults are those of transformers' LlamaConfig, which save_pretrained may omit.
  DecoderConfig c;
  c.hidden = json_get_or<int64_t>(j, "hidden_size", 4096, where);
  c.intermediate = json_get_or<int64_t>(j, "intermediate_size", 11008, where);
  c.layers = json_get_or<int64_t>(j, "num_hidden_layers", 32, where);
  c.heads = json_get_or<int64_t>(j, "num_attention_heads", 32, where);
  c.kv_heads = json_get_or<int64_t>(j, "num_key_value_heads", c.heads, where);
  c.head_dim = json_get_or<int64_t>(j, "head_dim", c.hidden / c.heads, where);
  c.vocab = json_get_or<int64_t>(j, "vocab_size", 32000, where);
  c.rms_norm_eps = json_get_or<float>(j, "rms_norm_eps", 1e-6f, where);
  c.attention_bias = json_get_or<bool>(j, "attention_bias", false, where);
  c.mlp_bias = json_get_or<bool>(j, "mlp_bias", false, where);
  const std::string act = json_get_or<std::string>(j, "hidden_act", "silu", where);
  if (act != "silu") throw Error(ErrorCode::unsupported, where + ": text hidden_act '" + act + "' (only silu)");
  if (c.heads % c.kv_heads != 0)
    throw Error(ErrorCode::format, where + ": num_attention_heads is not a multiple of num_key_value_heads");
  return c;
}

void KvCache::resize(backend::Backend& be, int64_t layers, int64_t batch_size, int64_t cap, int64_t width) {
  batch = batch_size;
  capacity = cap;
  kv_dim = width;
  k.clear();
  v.clear();
  for (int64_t i = 0; i < layers; ++i) {
    k.push_back(be.alloc<float>(batch * capacity * kv_dim));
    v.push_back(be.alloc<float>(batch * capacity * kv_dim));
  }
}

void DecoderLayer::load(backend::Backend& be, Weights& w, const std::string& p, const DecoderConfig& cfg,
                        int64_t hidden_size, int64_t intermediate_size, int64_t kv_input, Attention kind,
                        cpu::Precision precision, bool kv_only) {
  hidden = hidden_size;
  intermediate = intermediate_size;
  q_dim = cfg.heads * cfg.head_dim;
  kv_dim = cfg.kv_heads * cfg.head_dim;
  kv_in = kv_input;
  attention = kind;
  norm = cfg.norm;
  mlp = cfg.mlp;
  if (norm == NormKind::adaptive_rms) {
    if (cfg.cond_dim <= 0) throw Error(ErrorCode::format, p + ": adaptive norms need a conditioning width");
    input_mod = load_linear(be, w, p + "input_layernorm.dense", 3 * hidden, cfg.cond_dim, true, precision);
    if (!kv_only) post_mod = load_linear(be, w, p + "post_attention_layernorm.dense", 3 * hidden, cfg.cond_dim, true, precision);
  } else {
    input_norm = be.constant(w.f32(p + "input_layernorm.weight", {hidden}), hidden);
    post_norm = be.constant(w.f32(p + "post_attention_layernorm.weight", {hidden}), hidden);
  }
  if (cfg.qk_norm) {
    q_norm = be.constant(w.f32(p + "self_attn.q_norm.weight", {cfg.head_dim}), cfg.head_dim);
    k_norm = be.constant(w.f32(p + "self_attn.k_norm.weight", {cfg.head_dim}), cfg.head_dim);
  }

  const std::string q = p + "self_attn.q_proj", k = p + "self_attn.k_proj", v = p + "self_attn.v_proj";
  const bool bias = cfg.attention_bias;
  if (cross()) {
    qkv = load_linear(be, w, q, q_dim, hidden, bias, precision);
    k_in = load_linear(be, w, k, kv_dim, kv_in, bias, precision);
    v_in = load_linear(be, w, v, kv_dim, kv_in, bias, precision);
  } else if (kv_only) {
    kv = load_stacked_linear(be, w, {{k, kv_dim}, {v, kv_dim}}, kv_in, bias, precision);
  } else {
    qkv = load_stacked_linear(be, w, {{q, q_dim}, {k, kv_dim}, {v, kv_dim}}, hidden, bias, precision);
  }
  if (kv_only) return;  // the output of this layer is never read: no o_proj or MLP needed
  o = load_linear(be, w, p + "self_attn.o_proj", hidden, q_dim, bias, precision);
  gate_up = load_stacked_linear(be, w, {{p + "mlp.gate_proj", intermediate}, {p + "mlp.up_proj", intermediate}}, hidden,
                                cfg.mlp_bias, precision);
  down = load_linear(be, w, p + "mlp.down_proj", hidden, intermediate, cfg.mlp_bias, precision);
}

LayerFlops DecoderLayer::flops(int64_t rows, int64_t keys, int64_t heads, int64_t head_dim) const {
  LayerFlops f;
  for (const auto* lin : {&qkv, &kv, &o, &gate_up, &down})  // adaptive norms' dense layers run per item, not per row
    if (*lin) f.linear += linear_flops(**lin, rows);
  f.attention = kv ? 0.0 : 4.0 * double(rows) * double(keys) * double(heads) * double(head_dim);
  return f;
}

void DecoderScratch::reserve(backend::Backend& be, int64_t rows, int64_t hidden, int64_t q_dim, int64_t kv_dim,
                             int64_t intermediate) {
  auto grow = [&](backend::Array<float>& a, int64_t n) {
    if (a.size() < n) a = be.alloc<float>(n);
  };
  grow(normed, rows * hidden);
  grow(qkv, rows * (q_dim + 2 * kv_dim));
  grow(q, rows * q_dim);
  grow(attn, rows * q_dim);
  grow(mlp, rows * 3 * intermediate);
  grow(branch, rows * hidden);
}

namespace {
backend::RmsScale rms_scale(NormKind k) {
  return k == NormKind::rms_one_plus ? backend::RmsScale::one_plus_weight : backend::RmsScale::weight;
}
Activation mlp_activation(MlpKind k) { return k == MlpKind::swiglu ? Activation::silu : Activation::gelu_tanh; }
}  // namespace

void norm_input(backend::Backend& be, const DecoderLayer& L, const DecoderConfig& cfg, Ptr<const float> x, int64_t rows,
                Ptr<float> out, const Conditioning* c) {
  if (L.norm != NormKind::adaptive_rms) {
    be.rms_norm(x, rows, L.hidden, L.input_norm.at(), cfg.rms_norm_eps, out, rms_scale(L.norm));
    return;
  }
  if (!c || !c->input) throw Error(ErrorCode::internal, "decoder: an adaptive norm without its conditioning");
  const int64_t h = L.hidden;
  be.rms_norm_modulated(x, rows, h, c->input, c->input + h, 0, rows, cfg.rms_norm_eps, out);
}

void finish_layer(backend::Backend& be, const DecoderLayer& L, const DecoderConfig& cfg, Ptr<const float> attn,
                  int64_t rows, Ptr<float> x, DecoderScratch& s, const Conditioning* c) {
  const Ptr<float> normed = s.normed.at(), gu = s.mlp.at(), act = s.mlp.at(rows * 2 * L.intermediate);
  if (L.norm != NormKind::adaptive_rms) {
    be.linear(*L.o, attn, rows, x, /*accumulate=*/true);
    be.rms_norm(x, rows, L.hidden, L.post_norm.at(), cfg.rms_norm_eps, normed, rms_scale(L.norm));
    be.linear(*L.gate_up, normed, rows, gu);
    be.gated(gu, rows, L.intermediate, mlp_activation(L.mlp), act);
    be.linear(*L.down, act, rows, x, /*accumulate=*/true);
    return;
  }
  // Adaptive (pi0.5's expert): each residual branch is multiplied by the gate of the norm before it.
  const int64_t h = L.hidden;
  be.linear(*L.o, attn, rows, s.branch.at());
  be.gated_add(x, s.branch.at(), c->input + 2 * h, 0, rows, h, rows);
  be.rms_norm_modulated(x, rows, h, c->post, c->post + h, 0, rows, cfg.rms_norm_eps, normed);
  be.linear(*L.gate_up, normed, rows, gu);
  be.gated(gu, rows, L.intermediate, mlp_activation(L.mlp), act);
  be.linear(*L.down, act, rows, s.branch.at());
  be.gated_add(x, s.branch.at(), c->post + 2 * h, 0, rows, h, rows);
}

void DecoderStack::load(backend::Backend& be, Weights& w, const std::string& prefix, const DecoderConfig& cfg,
                        int64_t layers, cpu::Precision precision, bool last_kv_only) {
  cfg_ = cfg;
  layers_.resize(std::size_t(layers));
  for (int64_t i = 0; i < layers; ++i)
    layers_[i].load(be, w, prefix + std::to_string(i) + ".", cfg, cfg.hidden, cfg.intermediate, cfg.hidden,
                    DecoderLayer::Attention::self, precision, last_kv_only && i + 1 == layers);
}

void DecoderStack::forward(backend::Backend& be, Ptr<float> x, int64_t B, int64_t len, Ptr<const int64_t> positions,
                           Ptr<const uint8_t> mask, KvCache& cache) {
  run(be, x, B, len, positions, nullptr, mask, cache, nullptr);
}

void DecoderStack::forward(backend::Backend& be, Ptr<float> x, int64_t B, int64_t len, const RotaryTable& rotary,
                           Ptr<const uint8_t> mask, KvCache& cache, const std::function<void(int64_t layer)>& after_layer) {
  run(be, x, B, len, Ptr<const int64_t>(), &rotary, mask, cache, after_layer ? &after_layer : nullptr);
}

void DecoderStack::run(backend::Backend& be, Ptr<float> x, int64_t B, int64_t len, Ptr<const int64_t> positions,
                       const RotaryTable* rotary, Ptr<const uint8_t> mask, KvCache& cache,
                       const std::function<void(int64_t layer)>* after_layer) {
  const int64_t D = cfg_.hidden, H = cfg_.heads, KvH = cfg_.kv_heads, hd = cfg_.head_dim;
  const int64_t q_dim = H * hd, kv_dim = KvH * hd, rows = B * len;
  if (cache.batch != B || cache.capacity < len || cache.kv_dim != kv_dim || int64_t(cache.k.size()) < layers())
    throw Error(ErrorCode::internal, "decoder: the K/V cache does not fit this batch");
  scratch_.reserve(be, rows, D, q_dim, kv_dim, cfg_.intermediate);
  const float scale_qk = 1.0f / std::sqrt(float(hd));
  // Rotates `heads` heads of `n` tokens of item b in place, by position or by the given angles.
  const auto rotate = [&](Ptr<float> t, int64_t b, int64_t n, int64_t heads) {
    if (rotary) be.rope_rotate(t, n, heads, hd, rotary->cos + b * len * (hd / 2), rotary->sin + b * len * (hd / 2));
    else be.rope(t, 1, n, heads, hd, positions + b * len, cfg_.rope_wavelength, cfg_.rope_angles);
  };
  for (std::size_t li = 0; li < layers_.size(); ++li) {
    const DecoderLayer& L = layers_[li];
    const bool kv_only = bool(L.kv);
    norm_input(be, L, cfg_, x, rows, scratch_.normed.at());
    be.linear(kv_only ? *L.kv : *L.qkv, scratch_.normed.at(), rows, scratch_.qkv.at());
    const int64_t stride = kv_only ? 2 * kv_dim : q_dim + 2 * kv_dim, k_off = kv_only ? 0 : q_dim;
    if (!kv_only) {
      be.copy_rows(scratch_.qkv.at(), stride, scratch_.q.at(), q_dim, rows, q_dim);
      if (cfg_.qk_norm) be.rms_norm(scratch_.q.at(), rows * H, hd, L.q_norm.at(), cfg_.rms_norm_eps, scratch_.q.at());
    }
    for (int64_t b = 0; b < B; ++b) {
      const Ptr<float> kc = cache.k_at(int64_t(li), b, 0), vc = cache.v_at(int64_t(li), b, 0);
      be.copy_rows(scratch_.qkv.at(b * len * stride + k_off), stride, kc, kv_dim, len, kv_dim);
      be.copy_rows(scratch_.qkv.at(b * len * stride + k_off + kv_dim), stride, vc, kv_dim, len, kv_dim);
      if (cfg_.qk_norm) be.rms_norm(kc, len * KvH, hd, L.k_norm.at(), cfg_.rms_norm_eps, kc);
      rotate(kc, b, len, KvH);
      if (kv_only) continue;
      rotate(scratch_.q.at(b * len * q_dim), b, len, H);
      be.attention(scratch_.q.at(b * len * q_dim), q_dim, kc, vc, kv_dim, mask + b * len * len, 1, len, len, H, KvH, hd,
                   scale_qk, scratch_.attn.at(b * len * q_dim));
    }
    if (!kv_only) finish_layer(be, L, cfg_, scratch_.attn.at(), rows, x, scratch_);
    if (after_layer) (*after_layer)(int64_t(li));
  }
}

LayerFlops DecoderStack::flops(int64_t batch, int64_t len) const {
  LayerFlops f;
  for (const DecoderLayer& L : layers_) {
    const LayerFlops l = L.flops(batch * len, len, cfg_.heads, cfg_.head_dim);
    f.linear += l.linear;
    f.attention += l.attention;
  }
  return f;
}

}  // namespace tether::models
