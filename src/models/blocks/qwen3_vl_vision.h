// Qwen3-VL's vision tower (GR00T N1.7's Cosmos-Reason2 backbone): patch rows embedded by one matrix, a learned position
// table bilinearly resized to each image's grid, 2-D rotary attention within each image, DeepStack mergers on chosen
// blocks and the final 2x2 patch merger. Input rows come in merge-block order (vision/gr00t_preprocess.h), so four
// consecutive rows are one merged token.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "backend/backend.h"
#include "core/json_util.h"
#include "models/weights.h"

namespace tether::models {

struct Qwen3VisionConfig {
  int64_t depth = 27, hidden = 1152, intermediate = 4304, heads = 16, channels = 3, patch = 16, temporal_patch = 2,
          merge = 2, out_hidden = 3584, num_position_embeddings = 2304;
  std::vector<int64_t> deepstack_indexes = {8, 16, 24};
  float layer_norm_eps = 1e-6f;
  int64_t head_dim() const { return hidden / heads; }
  int64_t patch_values() const { return channels * temporal_patch * patch * patch; }  // one pixel row
  int64_t grid_side() const;  // the position table is grid_side x grid_side
  // Reads transformers' Qwen3VLVisionConfig (`vision_config`); absent fields take that class's defaults.
  static Qwen3VisionConfig from_json(const Json& j, const std::string& where);
};

// One image's patch grid (its pixel rows are h * w of them; t is 1 for a still image).
struct VisionGrid {
  int64_t t = 1, h = 0, w = 0;
  int64_t patches() const { return t * h * w; }
};

class Qwen3VisionTower {
 public:
  void load(backend::Backend& be, Weights& weights, const std::string& prefix, const Qwen3VisionConfig& config,
            cpu::Precision precision);
  const Qwen3VisionConfig& config() const { return cfg_; }
  int64_t deepstack_count() const { return int64_t(deepstack_.size()); }

  // pixels [sum patches, patch_values] of the images in `grids`, in order -> merged [sum patches / merge^2, out_hidden]
  // and, for each DeepStack merger k, deepstack[k] the same shape. `patch_embeds`, when set, receives the rows after
  // the position embedding is added (for parity dumps).
  void forward(backend::Backend& be, backend::Ptr<const float> pixels, const std::vector<VisionGrid>& grids,
               backend::Ptr<float> merged, const std::vector<backend::Ptr<float>>& deepstack,
               backend::Ptr<float> patch_embeds = {});
  double flops(const std::vector<VisionGrid>& grids) const;

 private:
  struct Block {
    backend::Array<float> ln1_w, ln1_b, ln2_w, ln2_b;
    std::unique_ptr<backend::LinearWeights> qkv, proj, fc1, fc2;
  };
  struct Merger {  // LayerNorm (before or after the 2x2 merge), fc1, exact GELU, fc2
    bool norm_after_merge = false;
    backend::Array<float> ln_w, ln_b;
    std::unique_ptr<backend::LinearWeights> fc1, fc2;
  };
  void load_merger(backend::Backend& be, Weights& w, const std::string& prefix, bool norm_after_merge,
                   cpu::Precision precision, Merger& m);
  void run_merger(backend::Backend& be, const Merger& m, backend::Ptr<const float> x, int64_t patches,
                  backend::Ptr<float> out);
  // Position rows and rotary angles for a list of grids, computed on the host once per distinct list.
  void prepare_positions(backend::Backend& be, const std::vector<VisionGrid>& grids);

  Qwen3VisionConfig cfg_;
  std::unique_ptr<backend::LinearWeights> patch_embed_;
  std::vector<float> pos_table_;  // [grid_side^2, hidden], float32
  std::vector<Block> blocks_;
  std::vector<Merger> deepstack_;  // one per entry of deepstack_indexes
  Merger merger_;

  std::vector<VisionGrid> prepared_for_;
  backend::Array<float> pos_rows_, rot_cos_, rot_sin_;
  backend::Array<float> x_, normed_, qkv_, q_, k_, v_, attn_, mlp_, merge_tmp_;
};

}  // namespace tether::models
