// Diffusion-transformer blocks against the backend interface (see dit.h).
#include "models/blocks/dit.h"

#include <cmath>

#include "core/error.h"
#include "models/blocks/linear.h"

namespace tether::models {

using backend::Activation;
using backend::Ptr;

void DitBlock::load(backend::Backend& be, Weights& w, const std::string& p, int64_t dim_, int64_t heads_,
                    int64_t head_dim_, int64_t kv_in_, bool adaptive_, bool affine, cpu::Precision precision) {
  dim = dim_;
  heads = heads_;
  head_dim = head_dim_;
  kv_in = kv_in_;
  cross = kv_in_ > 0;
  adaptive = adaptive_;
  inner = 4 * dim;
  if (heads * head_dim != dim)
    throw Error(ErrorCode::format, p + ": " + std::to_string(heads) + " heads of " + std::to_string(head_dim) +
                                       " do not make the block width " + std::to_string(dim));
  if (adaptive) {
    ada = load_linear(be, w, p + "norm1.linear", 2 * dim, dim, true, precision);
  } else if (affine) {
    ln1_w = be.constant(w.f32(p + "norm1.weight", {dim}), dim);
    ln1_b = be.constant(w.f32(p + "norm1.bias", {dim}), dim);
  }
  if (affine) {
    ln3_w = be.constant(w.f32(p + "norm3.weight", {dim}), dim);
    ln3_b = be.constant(w.f32(p + "norm3.bias", {dim}), dim);
  }
  const std::string a = p + "attn1.";
  if (cross) {
    q = load_linear(be, w, a + "to_q", dim, dim, true, precision);
    kv = load_stacked_linear(be, w, {{a + "to_k", dim}, {a + "to_v", dim}}, kv_in, true, precision);
  } else {
    qkv = load_stacked_linear(be, w, {{a + "to_q", dim}, {a + "to_k", dim}, {a + "to_v", dim}}, dim, true, precision);
  }
  out = load_linear(be, w, a + "to_out.0", dim, dim, true, precision);
  ff1 = load_linear(be, w, p + "ff.net.0.proj", inner, dim, true, precision);
  ff2 = load_linear(be, w, p + "ff.net.2", dim, inner, true, precision);
}

void DitScratch::reserve(backend::Backend& be, int64_t rows, int64_t dim, int64_t inner) {
  auto grow = [&](backend::Array<float>& a, int64_t n) {
    if (a.size() < n) a = be.alloc<float>(n);
  };
  grow(normed, rows * dim);
  grow(q, rows * dim);
  grow(qkv, rows * 3 * dim);
  grow(attn, rows * dim);
  grow(ff, rows * inner);
}

void dit_block_forward(backend::Backend& be, const DitBlock& B, const DitContext& ctx, Ptr<float> x, const CrossKv* kv,
                       Ptr<const uint8_t> mask, DitScratch& s) {
  const int64_t rows = ctx.batch * ctx.rows, D = B.dim;
  const float scale = 1.0f / std::sqrt(float(B.head_dim));
  if (B.adaptive) {
    // LayerNorm without affine, then * (1 + scale) + shift, one [scale | shift] row for the whole batch.
    be.layer_norm(x, rows, D, Ptr<const float>(), Ptr<const float>(), ctx.eps, s.normed.at());
    be.modulate(s.normed.at(), rows, D, ctx.modulation, ctx.modulation + D, 0, rows);
  } else {
    be.layer_norm(x, rows, D, B.ln1_w.at(), B.ln1_b.at(), ctx.eps, s.normed.at());
  }
  if (B.cross) {
    if (!kv) throw Error(ErrorCode::internal, "dit: a cross-attention block without its keys and values");
    be.linear(*B.q, s.normed.at(), rows, s.q.at());
    be.attention(s.q.at(), D, kv->kv.at(), kv->kv.at(D), 2 * D, mask, ctx.batch, ctx.rows, kv->len, B.heads, B.heads,
                 B.head_dim, scale, s.attn.at());
  } else {
    be.linear(*B.qkv, s.normed.at(), rows, s.qkv.at());
    be.attention(s.qkv.at(), 3 * D, s.qkv.at(D), s.qkv.at(2 * D), 3 * D, mask, ctx.batch, ctx.rows, ctx.rows, B.heads,
                 B.heads, B.head_dim, scale, s.attn.at());
  }
  be.linear(*B.out, s.attn.at(), rows, x, /*accumulate=*/true);
  be.layer_norm(x, rows, D, B.ln3_w.at(), B.ln3_b.at(), ctx.eps, s.normed.at());
  be.linear(*B.ff1, s.normed.at(), rows, s.ff.at());
  be.activate(s.ff.at(), rows * B.inner, Activation::gelu_tanh);
  be.linear(*B.ff2, s.ff.at(), rows, x, /*accumulate=*/true);
}

DitConfig DitConfig::from_json(const Json& j, int64_t cross_dim, bool alternate_vl, int64_t attend_text_every_n_blocks,
                               const std::string& where) {
  DitConfig c;
  c.layers = json_get_or<int64_t>(j, "num_layers", c.layers, where);
  c.heads = json_get_or<int64_t>(j, "num_attention_heads", c.heads, where);
  c.head_dim = json_get_or<int64_t>(j, "attention_head_dim", c.head_dim, where);
  c.output_dim = json_get_or<int64_t>(j, "output_dim", c.output_dim, where);
  c.interleave_self_attention = json_get_or<bool>(j, "interleave_self_attention", false, where);
  c.cross_dim = cross_dim;
  c.alternate_vl = alternate_vl;
  c.attend_text_every_n_blocks = attend_text_every_n_blocks;
  const std::string norm = json_get_or<std::string>(j, "norm_type", "ada_norm", where);
  if (norm != "ada_norm") throw Error(ErrorCode::unsupported, where + ": norm_type '" + norm + "' (only ada_norm)");
  const std::string act = json_get_or<std::string>(j, "activation_fn", "gelu-approximate", where);
  if (act != "gelu-approximate")
    throw Error(ErrorCode::unsupported, where + ": activation_fn '" + act + "' (only gelu-approximate)");
  if (j.contains("positional_embeddings") && !j.at("positional_embeddings").is_null())
    throw Error(ErrorCode::unsupported, where + ": positional_embeddings in the DiT blocks (only null)");
  if (alternate_vl && !c.interleave_self_attention)
    throw Error(ErrorCode::format, where + ": the alternating DiT needs interleave_self_attention");
  if (c.attend_text_every_n_blocks < 1)
    throw Error(ErrorCode::format, where + ": attend_text_every_n_blocks must be >= 1");
  return c;
}

void DiTStack::load(backend::Backend& be, Weights& w, const std::string& p, const DitConfig& cfg,
                    cpu::Precision precision) {
  cfg_ = cfg;
  const int64_t D = cfg.dim();
  time_1_ = load_linear(be, w, p + "timestep_encoder.timestep_embedder.linear_1", D, 256, true, precision);
  time_2_ = load_linear(be, w, p + "timestep_encoder.timestep_embedder.linear_2", D, D, true, precision);
  blocks_.resize(std::size_t(cfg.layers));
  for (int64_t i = 0; i < cfg.layers; ++i) {
    const bool self = cfg.interleave_self_attention && i % 2 == 1;
    blocks_[std::size_t(i)].load(be, w, p + "transformer_blocks." + std::to_string(i) + ".", D, cfg.heads, cfg.head_dim,
                                 self ? 0 : cfg.cross_dim, /*adaptive=*/true, /*affine=*/false, precision);
  }
  proj_out_1_ = load_linear(be, w, p + "proj_out_1", 2 * D, D, true, precision);
  proj_out_2_ = load_linear(be, w, p + "proj_out_2", cfg.output_dim, D, true, precision);
}

void diffusers_timestep_sinusoid(int64_t timestep, int64_t channels, float* out) {
  const int64_t half = channels / 2;
  // exponent = -ln(10000) * arange(half) in float32, divided by (half - 1); exp; times the timestep; [sin | cos] flipped
  // to [cos | sin].
  const float neg_log = float(-std::log(10000.0));
  for (int64_t k = 0; k < half; ++k) {
    const float exponent = (neg_log * float(k)) / float(half - 1);
    const float arg = float(timestep) * std::exp(exponent);
    out[k] = std::cos(arg);
    out[half + k] = std::sin(arg);
  }
}

void DiTStack::time_embedding(backend::Backend& be, int64_t bucket, int64_t B, Ptr<float> temb) {
  const int64_t D = cfg_.dim();
  host_sinusoid_.resize(256);
  diffusers_timestep_sinusoid(bucket, 256, host_sinusoid_.data());
  if (time_in_.size() < B * 256) time_in_ = be.alloc<float>(B * 256);
  if (time_mid_.size() < B * D) time_mid_ = be.alloc<float>(B * D);
  be.upload(host_sinusoid_.data(), 256, time_in_.at());
  be.copy_rows(time_in_.at(), 0, time_in_.at(256), 256, B - 1, 256);  // every item has the same bucket
  be.linear(*time_1_, time_in_.at(), B, time_mid_.at());
  be.activate(time_mid_.at(), B * D, Activation::silu);
  be.linear(*time_2_, time_mid_.at(), B, temb);
}

void DiTStack::project_context(backend::Backend& be, Ptr<const float> context, int64_t batch, int64_t len,
                               std::vector<CrossKv>& kv) {
  kv.resize(blocks_.size());
  for (std::size_t i = 0; i < blocks_.size(); ++i) {
    if (!blocks_[i].cross) continue;
    CrossKv& c = kv[i];
    if (c.kv.size() < batch * len * 2 * cfg_.dim()) c.kv = be.alloc<float>(batch * len * 2 * cfg_.dim());
    c.len = len;
    be.linear(*blocks_[i].kv, context, batch * len, c.kv.at());
  }
}

Ptr<const float> DiTStack::time_modulation(backend::Backend& be, int64_t bucket) {
  const int64_t D = cfg_.dim(), row = 2 * D, n = int64_t(blocks_.size()) + 1;
  return modulation_.get(be, bucket, n * row, [&](Ptr<float> mod) {
    // silu(temb) for one item: the batch shares its time.
    if (silu_temb_.size() < D) silu_temb_ = be.alloc<float>(D);
    time_embedding(be, bucket, 1, silu_temb_.at());
    be.activate(silu_temb_.at(), D, Activation::silu);
    for (std::size_t i = 0; i < blocks_.size(); ++i)
      if (blocks_[i].adaptive) be.linear(*blocks_[i].ada, silu_temb_.at(), 1, mod + int64_t(i) * row);
    be.linear(*proj_out_1_, silu_temb_.at(), 1, mod + (n - 1) * row);
  });
}

void DiTStack::forward(backend::Backend& be, Ptr<float> x, int64_t batch, int64_t rows, int64_t bucket,
                       const std::vector<CrossKv>& kv, const std::vector<Ptr<const uint8_t>>& masks, Ptr<float> out) {
  const int64_t D = cfg_.dim();
  scratch_.reserve(be, batch * rows, D, 4 * D);
  const Ptr<const float> mod = time_modulation(be, bucket);
  DitContext ctx{batch, rows, Ptr<const float>(), 1e-5f};
  for (std::size_t i = 0; i < blocks_.size(); ++i) {
    ctx.modulation = mod + int64_t(i) * 2 * D;
    dit_block_forward(be, blocks_[i], ctx, x, blocks_[i].cross ? &kv[i] : nullptr,
                      i < masks.size() ? masks[i] : Ptr<const uint8_t>(), scratch_);
  }
  // Output: (shift, scale) = proj_out_1(silu(temb)); LayerNorm (eps 1e-6, no affine) * (1 + scale) + shift.
  const Ptr<const float> out_mod = mod + int64_t(blocks_.size()) * 2 * D;
  be.layer_norm(x, batch * rows, D, Ptr<const float>(), Ptr<const float>(), 1e-6f, scratch_.normed.at());
  be.modulate(scratch_.normed.at(), batch * rows, D, out_mod + D, out_mod, 0, batch * rows);
  be.linear(*proj_out_2_, scratch_.normed.at(), batch * rows, out);
}

double DiTStack::flops(int64_t batch, int64_t rows, int64_t context_len) const {
  double f = 0;
  const int64_t n = batch * rows, D = cfg_.dim();
  for (const DitBlock& B : blocks_) {
    f += linear_flops(*B.out, n) + linear_flops(*B.ff1, n) + linear_flops(*B.ff2, n);
    f += B.cross ? linear_flops(*B.q, n) : linear_flops(*B.qkv, n);
    f += 4.0 * double(n) * double(B.cross ? context_len : rows) * double(D);
  }
  return f + linear_flops(*proj_out_2_, n);
}

void SelfAttentionStack::load(backend::Backend& be, Weights& w, const std::string& p, int64_t layers, int64_t heads,
                              int64_t head_dim, cpu::Precision precision) {
  blocks_.resize(std::size_t(layers));
  for (int64_t i = 0; i < layers; ++i)
    blocks_[std::size_t(i)].load(be, w, p + "transformer_blocks." + std::to_string(i) + ".", heads * head_dim, heads,
                                 head_dim, 0, /*adaptive=*/false, /*affine=*/true, precision);
}

void SelfAttentionStack::forward(backend::Backend& be, Ptr<float> x, int64_t batch, int64_t rows) {
  if (blocks_.empty()) return;
  const int64_t D = blocks_[0].dim;
  scratch_.reserve(be, batch * rows, D, 4 * D);
  const DitContext ctx{batch, rows, Ptr<const float>(), 1e-5f};
  for (const DitBlock& B : blocks_) dit_block_forward(be, B, ctx, x, nullptr, Ptr<const uint8_t>(), scratch_);
}

double SelfAttentionStack::flops(int64_t batch, int64_t rows) const {
  double f = 0;
  const int64_t n = batch * rows;
  for (const DitBlock& B : blocks_)
    f += linear_flops(*B.qkv, n) + linear_flops(*B.out, n) + linear_flops(*B.ff1, n) + linear_flops(*B.ff2, n) +
         4.0 * double(n) * double(rows) * double(B.dim);
  return f;
}

}  // namespace tether::models
