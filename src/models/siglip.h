// SigLIP-style vision tower as used by SmolVLM (Idefics3 vision transformer) and its pixel-shuffle connector.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "backend/cpu/packed_linear.h"
#include "core/json_util.h"
#include "models/weights.h"

namespace tether::models {

struct VisionConfig {
  int64_t hidden = 0, intermediate = 0, layers = 0, heads = 0, patch = 0, image_size = 0, channels = 3;
  float layer_norm_eps = 1e-6f;
  // Reads a transformers vision_config object; absent fields take the upstream class defaults.
  static VisionConfig from_json(const Json& j, const std::string& where);
};

class VisionTower {
 public:
  void load(Weights& weights, const std::string& prefix, const VisionConfig& config, cpu::Precision precision);

  int64_t hidden() const { return cfg_.hidden; }
  int64_t num_patches(int64_t height, int64_t width) const { return (height / cfg_.patch) * (width / cfg_.patch); }

  // pixels [B, C, H, W], H and W multiples of the patch size -> out [B, num_patches, hidden] after the final
  // layer norm.
  void forward(const float* pixels, int64_t batch, int64_t height, int64_t width, float* out);

 private:
  struct Layer {
    const float *ln1_w, *ln1_b, *ln2_w, *ln2_b;
    cpu::PackedLinear qkv;  // q, k and v stacked so one GEMM computes all three
    cpu::PackedLinear o, fc1, fc2;
  };
  void position_ids(int64_t patches_h, int64_t patches_w, std::vector<int64_t>& ids) const;

  VisionConfig cfg_;
  const float *patch_w_ = nullptr, *patch_b_ = nullptr, *pos_emb_ = nullptr;
  const float *post_ln_w_ = nullptr, *post_ln_b_ = nullptr;
  std::vector<Layer> layers_;
  std::vector<float> x_, normed_, qkv_, attn_, mlp_;  // activations, grown once per shape
  std::vector<int64_t> pos_ids_;
};

// Idefics3/SmolVLM connector: pixel shuffle by `scale_factor`, then a bias-free projection to the text width.
class PixelShuffleConnector {
 public:
  void load(Weights& weights, const std::string& prefix, int64_t vision_hidden, int64_t scale_factor,
            int64_t text_hidden, cpu::Precision precision);
  int64_t tokens(int64_t patches) const { return patches / (scale_ * scale_); }
  // x [B, patches, vision_hidden] -> out [B, patches / scale^2, text_hidden]
  void forward(const float* x, int64_t batch, int64_t patches, float* out);

 private:
  int64_t vision_hidden_ = 0, scale_ = 1, text_hidden_ = 0;
  cpu::PackedLinear proj_;
  std::vector<float> shuffled_;
};

}  // namespace tether::models
