// NVIDIA's GR00T N1.7 (lerobot's GR00TN17 with its N1.7 pre- and post-processing): a Qwen3-VL backbone (Cosmos-Reason2)
// cut at `select_layer`, a VL self-attention over its features, and a flow-matching action head whose DiT alternates
// cross-attention to text and image tokens, with per-embodiment state/action encoders and decoder.
#pragma once

#include <filesystem>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "models/family.h"
#include "models/normalization.h"

namespace tether::models {

// The families' descriptors (gr00t_family.cpp): raw NVIDIA checkpoints with config.json model_type "Gr00tN1d7"
// (N1.7) or "Gr00tN1d6" (N1.6).
const FamilyDescriptor& gr00t_n17_family();
const FamilyDescriptor& gr00t_n16_family();

// One embodiment of a checkpoint, as processor_config.json's modality config, statistics.json and
// embodiment_id.json describe it.
struct Gr00tEmbodiment {
  std::string tag;
  int64_t id = 0;                    // row of the per-embodiment weights
  std::vector<std::string> cameras;  // video.modality_keys, in the model's order
  Json modality_config;              // processor_config.json's modality_configs[tag], as it is
  std::vector<ModalityGroup> state_groups, action_groups;
  int64_t action_horizon = 0;        // len(action.delta_indices): the rows a chunk keeps
  // Bounds per group (q01/q99 with use_percentiles, else min/max), concatenated in group order. The action bounds
  // hold `action_bound_rows` rows: 1, or the chunk's rows when a relative group has per-step statistics.
  std::vector<float> state_lo, state_hi, action_lo, action_hi;
  int64_t action_bound_rows = 1;
  // With use_relative_action: the action groups predicted relative to the state (lerobot's
  // GrootN17ActionDecodeStep), unnormalised with relative_action's min/max and made absolute against the state.
  std::vector<RelativeAction> relative;
  // N1.6 only: action groups listed in the action modality's mean_std_embedding_keys, which Isaac-GR00T's
  // StateActionProcessor decodes as x * std + mean (x where std is 0), unclipped. One row: per column a 1 in
  // action_mean_std where that applies, and its mean and std; empty when no group is listed.
  std::vector<float> action_mean_std, action_mean, action_std;
};

// A sidecar file of a raw GR00T checkpoint (processor_config.json, statistics.json, embodiment_id.json): in the
// checkpoint's root, as NVIDIA's releases have them, else in its `processor/` sub-folder, where Isaac-GR00T's training
// runs write them. Neither present: the root path, for the error to name.
std::filesystem::path gr00t_sidecar(const std::filesystem::path& dir, const std::string& name);

// The embodiment `tag` of the checkpoint in `dir` (empty: its only one); errors list the tags it has.
Gr00tEmbodiment read_gr00t_embodiment(const std::filesystem::path& dir, const std::string& tag);

// lerobot's N1.7 language formalisation: lower case, keep only letters, numbers, whitespace and "_"; an empty
// instruction is "Perform the task." first.
std::string gr00t_formalize_language(const std::string& instruction, bool formalize);

// N1.6's prompt as Isaac-GR00T renders it: the Eagle chat template over one user turn holding the (formalised)
// language then each image, whose "<image-k>" placeholder the Eagle processor expands to "<image k><img>", one
// <IMG_CONTEXT> per projected token, "</img>". A resized frame of height x width has (height / 28) * (width / 28)
// such tokens (patch 14, then the 2x2 pixel unshuffle).
int64_t gr00t_n16_image_tokens(int64_t height, int64_t width);
std::string gr00t_n16_prompt(const std::string& language, const std::vector<int64_t>& image_tokens);

// lerobot's N1.7 decode step, for the `libero_sim` tag only, maps the gripper group g to -sign(2g - 1) after
// unnormalising (the LIBERO simulator's open/close convention). Tether serves robot units and leaves that mapping to
// the client; comparisons with lerobot's decoded actions apply it to Tether's. `actions` is [rows, action_dim].
bool gr00t_applies_libero_transform(const std::string& embodiment_tag);
void libero_gripper_transform(std::vector<float>& actions, const std::vector<ModalityGroup>& action_groups);

// True when two loaded models are embodiments of one shared GR00T checkpoint (its weights held once).
bool gr00t_shares_weights(const Model& a, const Model& b);

std::unique_ptr<Model> load_gr00t_n16(const std::filesystem::path& dir, const Json& config, TensorStore weights,
                                      const LoadOptions& options);
std::unique_ptr<Model> load_gr00t_n17(const std::filesystem::path& dir, const Json& config, TensorStore weights,
                                      const LoadOptions& options);

}  // namespace tether::models
