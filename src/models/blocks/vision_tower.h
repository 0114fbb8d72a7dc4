// SigLIP vision towers (SmolVLM's Idefics3 variant, PaliGemma's SigLIP) and the pixel-shuffle connector, against the
// backend interface. The variants differ in patch size, how patches find their position embedding, and the post-norm.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "backend/backend.h"
#include "core/json_util.h"
#include "models/weights.h"

namespace tether::models {

struct VisionConfig {
  int64_t hidden = 0, intermediate = 0, layers = 0, heads = 0, patch = 0, image_size = 0, channels = 3;
  float layer_norm_eps = 1e-6f;
  // bucketed: Idefics3's fractional patch coordinates bucketised against the native grid, so a smaller image reuses
  // the native table. sequential: SigLIP's 0..patches-1, the image must have the native size.
  // sequential: SigLIP's 0..patches-1, the image must have the native size. resized: SigLIP2's learned square table
  // (table_side^2 rows) resized to the image's patch grid, bilinear with antialiasing as torch's F.interpolate.
  enum class PositionIds { bucketed, sequential, resized } position_ids = PositionIds::bucketed;
  int64_t table_side = 0;  // resized: the table's side (num_patches = table_side^2)
  bool post_norm = true;   // a final LayerNorm over the tower's output
  // SigLIP2 stores the patch embedding as a Linear over patches flattened (row, column, channel) instead of a conv.
  bool linear_patch_embedding = false;
  // Reads a transformers vision_config object; absent fields take the upstream class defaults (SmolVLM's).
  static VisionConfig from_json(const Json& j, const std::string& where);
  // Reads a SigLIP2 vision_config (Siglip2VisionConfig: num_patches, patch_size 16 by default).
  static VisionConfig from_siglip2_json(const Json& j, const std::string& where);
};

// torch's F.interpolate(mode="bilinear", align_corners=False, antialias=True) of a table of `side` x `side` rows of
// `d` values (row y * side + x) to `out_h` x `out_w` rows, in float32 as its CPU kernel computes it (the width pass
// first, then the height pass).
std::vector<float> resize_table_bilinear_aa(const float* table, int64_t side, int64_t d, int64_t out_h, int64_t out_w);

class VisionTower {
 public:
  void load(backend::Backend& be, Weights& weights, const std::string& prefix, const VisionConfig& config,
            cpu::Precision precision);

  int64_t hidden() const { return cfg_.hidden; }
  int64_t num_patches(int64_t height, int64_t width) const { return (height / cfg_.patch) * (width / cfg_.patch); }

  // pixels [B, C, H, W], H and W multiples of the patch size -> out [B, num_patches, hidden].
  void forward(backend::Backend& be, backend::Ptr<const float> pixels, int64_t batch, int64_t height, int64_t width,
               backend::Ptr<float> out);
  double flops(int64_t batch, int64_t height, int64_t width) const;

 private:
  struct Layer {
    backend::Array<float> ln1_w, ln1_b, ln2_w, ln2_b;
    std::unique_ptr<backend::LinearWeights> qkv;  // q, k and v stacked so one GEMM computes all three
    std::unique_ptr<backend::LinearWeights> o, fc1, fc2;
  };
  void position_ids(int64_t patches_h, int64_t patches_w, std::vector<int64_t>& ids) const;

  VisionConfig cfg_;
  backend::Array<float> patch_w_, patch_b_, post_ln_w_, post_ln_b_;
  std::unique_ptr<backend::Table> pos_emb_;
  std::vector<float> pos_table_;  // resized positions: the host table they are computed from
  std::vector<Layer> layers_;
  backend::Array<float> x_, normed_, qkv_, attn_, mlp_, pos_rows_;  // activations, grown once per shape
  backend::Array<int64_t> pos_ids_;
  int64_t pos_for_h_ = -1, pos_for_w_ = -1;  // the image size pos_rows_ was gathered for
};

// Idefics3/SmolVLM connector: pixel shuffle by `scale_factor`, then a bias-free projection to the text width.
class PixelShuffleConnector {
 public:
  void load(backend::Backend& be, Weights& weights, const std::string& prefix, int64_t vision_hidden,
            int64_t scale_factor, int64_t text_hidden, cpu::Precision precision);
  int64_t tokens(int64_t patches) const { return patches / (scale_ * scale_); }
  // x [B, patches, vision_hidden] -> out [B, patches / scale^2, text_hidden]
  void forward(backend::Backend& be, backend::Ptr<const float> x, int64_t batch, int64_t patches,
               backend::Ptr<float> out);
  double flops(int64_t batch, int64_t patches) const;

 private:
  int64_t vision_hidden_ = 0, scale_ = 1, text_hidden_ = 0;
  std::unique_ptr<backend::LinearWeights> proj_;
  backend::Array<float> shuffled_;
};

}  // namespace tether::models
