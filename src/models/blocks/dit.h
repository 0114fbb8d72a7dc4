// Diffusion-transformer blocks in the diffusers layout GR00T's action head uses: a block is a norm, one attention (to
// itself or to another stream's tokens, with a key mask), and a GELU-tanh feed-forward, each added back. The norm is a
// LayerNorm with affine weights, or an adaptive LayerNorm scaled and shifted by the time embedding ("ada_norm").
// DiTStack strings such blocks with the time encoder and the modulated output projection; SelfAttentionStack is the
// plain stack GR00T N1.7 runs over the backbone features.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "backend/backend.h"
#include "core/json_util.h"
#include "models/blocks/kept_per_time.h"
#include "models/weights.h"

namespace tether::models {

struct DitBlock {
  bool adaptive = false;  // ada_norm: norm1 is LayerNorm without affine, modulated by linear(silu(temb))
  bool cross = false;     // attention keys/values come from another stream of width kv_in
  int64_t dim = 0, heads = 0, head_dim = 0, kv_in = 0, inner = 0;
  backend::Array<float> ln1_w, ln1_b, ln3_w, ln3_b;   // affine norms (empty when adaptive / without affine)
  std::unique_ptr<backend::LinearWeights> ada;        // adaptive: temb -> [scale | shift]
  std::unique_ptr<backend::LinearWeights> q, kv, qkv;  // cross: q from x, kv = [k | v] from the other stream; self: qkv
  std::unique_ptr<backend::LinearWeights> out, ff1, ff2;
  // `affine`: the LayerNorms carry weights (norm1 unless adaptive, and norm3).
  void load(backend::Backend& be, Weights& w, const std::string& prefix, int64_t dim, int64_t heads, int64_t head_dim,
            int64_t kv_in, bool adaptive, bool affine, cpu::Precision precision);
};

// Scratch of a block pass, grown once per shape.
struct DitScratch {
  backend::Array<float> normed, q, qkv, attn, ff;
  void reserve(backend::Backend& be, int64_t rows, int64_t dim, int64_t inner);
};

// Keys and values of the other stream for one cross block, computed once per request: [batch, len, dim] each.
struct CrossKv {
  backend::Array<float> kv;  // [batch, len, k | v]
  int64_t len = 0;
};

// What the blocks attend to besides themselves: per cross block its keys/values and a key mask [batch, rows, len].
struct DitContext {
  int64_t batch = 0, rows = 0;  // tokens per item of x
  // Adaptive norms: the block's [scale | shift] [2 * dim] from linear(silu(time embedding)), shared by the batch
  // (every item is at the same time).
  backend::Ptr<const float> modulation;
  float eps = 1e-5f;
};

// One block over x [batch * rows, dim] in place. `kv`/`mask` only for cross blocks (mask null: attend everywhere).
void dit_block_forward(backend::Backend& be, const DitBlock& B, const DitContext& ctx, backend::Ptr<float> x,
                       const CrossKv* kv, backend::Ptr<const uint8_t> mask, DitScratch& s);

struct DitConfig {
  int64_t layers = 12, heads = 8, head_dim = 64, output_dim = 26, cross_dim = 0;
  bool interleave_self_attention = false;
  int64_t attend_text_every_n_blocks = 2;  // AlternateVLDiT: block i % (2n) == 0 reads text keys, else image keys
  bool alternate_vl = false;
  int64_t dim() const { return heads * head_dim; }
  // GR00T's diffusion_model_cfg plus the head's cross-attention width and AlternateVLDiT switch.
  static DitConfig from_json(const Json& j, int64_t cross_dim, bool alternate_vl, int64_t attend_text_every_n_blocks,
                             const std::string& where);
};

class DiTStack {
 public:
  void load(backend::Backend& be, Weights& w, const std::string& prefix, const DitConfig& cfg, cpu::Precision precision);
  const DitConfig& config() const { return cfg_; }
  bool cross(int64_t block) const { return blocks_[std::size_t(block)].cross; }
  int64_t layers() const { return int64_t(blocks_.size()); }

  // Every cross block's keys/values of `context` [batch, len, cross_dim]: constant over the denoising steps.
  void project_context(backend::Backend& be, backend::Ptr<const float> context, int64_t batch, int64_t len,
                       std::vector<CrossKv>& kv);
  // The timestep encoder for one integer bucket shared by the batch: sinusoid (cos first), linear, SiLU, linear ->
  // temb [batch, dim].
  void time_embedding(backend::Backend& be, int64_t bucket, int64_t batch, backend::Ptr<float> temb);
  // x [batch * rows, dim] at timestep `bucket` through every block, then the modulated output norm and projection ->
  // out [batch * rows, output_dim]. masks[i]: block i's key mask [batch, rows, len] (cross blocks; null: none).
  void forward(backend::Backend& be, backend::Ptr<float> x, int64_t batch, int64_t rows, int64_t bucket,
               const std::vector<CrossKv>& kv, const std::vector<backend::Ptr<const uint8_t>>& masks,
               backend::Ptr<float> out);
  double flops(int64_t batch, int64_t rows, int64_t context_len) const;

 private:
  DitConfig cfg_;
  std::vector<DitBlock> blocks_;
  std::unique_ptr<backend::LinearWeights> time_1_, time_2_, proj_out_1_, proj_out_2_;
  DitScratch scratch_;
  backend::Array<float> silu_temb_, time_in_, time_mid_;
  std::vector<float> host_sinusoid_;  // [256], reused by every step

  // What the timestep alone decides, for every item of every request: row i (2 * dim) is block i's [scale | shift],
  // the last row the output norm's [shift | scale], each linear(silu(time embedding)); kept per bucket.
  backend::Ptr<const float> time_modulation(backend::Backend& be, int64_t bucket);
  KeptPerTime<int64_t> modulation_;
};

// Layer-normed self-attention blocks with affine norms and no mask (GR00T N1.7's vl_self_attention).
class SelfAttentionStack {
 public:
  void load(backend::Backend& be, Weights& w, const std::string& prefix, int64_t layers, int64_t heads, int64_t head_dim,
            cpu::Precision precision);
  int64_t layers() const { return int64_t(blocks_.size()); }
  // x [batch * rows, dim] in place.
  void forward(backend::Backend& be, backend::Ptr<float> x, int64_t batch, int64_t rows);
  double flops(int64_t batch, int64_t rows) const;

 private:
  std::vector<DitBlock> blocks_;
  DitScratch scratch_;
};

// diffusers' Timesteps(num_channels, flip_sin_to_cos=True, downscale_freq_shift=1) of an integer timestep, in
// float32: [cos(t f_k), sin(t f_k)], f_k = exp(-ln(10000) k / (half - 1)).
void diffusers_timestep_sinusoid(int64_t timestep, int64_t channels, float* out);

}  // namespace tether::models
