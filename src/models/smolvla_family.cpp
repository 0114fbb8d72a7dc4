// SmolVLA's family descriptor: a lerobot checkpoint of type "smolvla" whose VLM backbone (config, tokenizer) is
// named by vlm_model_name and found beside the checkpoint or in the hub cache.
#include <filesystem>

#include "models/backbone.h"
#include "models/lerobot/checkpoint.h"
#include "models/smolvla.h"

namespace tether::models {

namespace fs = std::filesystem;

namespace {

bool recognises(const CheckpointProbe& p) { return lerobot::policy_type(p.config) == "smolvla"; }

std::vector<std::string> weight_files(const fs::path& dir) { return TensorStore::files_in(dir.string()); }

TensorStore open_weights(const fs::path& dir) { return TensorStore::open_dir(dir.string()); }

Normalization load_normalization(const fs::path& dir, const Json& config, TensorStore& weights, const LoadOptions&) {
  return lerobot::load_normalization(dir.string(), config, weights);
}

// Processor files copied; the backbone's files travel in vlm/ and the config names that folder.
ExportPlan export_plan(const fs::path& dir, const Json& config, const LoadOptions&) {
  ExportPlan plan;
  plan.copy = lerobot::processor_files(dir.string());
  const fs::path backbone =
      find_backbone_dir(dir, json_get<std::string>(config, "vlm_model_name", (dir / "config.json").string()));
  plan.bundles.push_back({backbone, "vlm", backbone_files(backbone)});
  plan.config = config;
  plan.config["vlm_model_name"] = "vlm";
  if (plan.copy.empty()) {  // pre-0.4 layout: the statistics inside the weights keep their float32
    const TensorStore weights = open_weights(dir);
    if (lerobot::has_legacy_stats(weights))
      plan.keep_dtype = lerobot::convert_legacy_stats(config, weights, weights.label()).stripped;
  }
  return plan;
}

const FamilyDescriptor kSmolVLA{
    .name = "smolvla",
    .summary = "SmolVLA (lerobot): SmolVLM vision tower and truncated SmolLM2 prefix, Llama action expert, "
               "flow-matching sampler",
    .recognition = "config.json \"type\": \"smolvla\", lerobot",
    .recognises = &recognises,
    .tokenizer = TokenizerKind::byte_level_bpe,
    .stages = {"preprocess", "vision", "prefix", "denoise"},
    .missing_camera_rule = "up to the config's empty_cameras absent cameras are filled with a masked -1 image, "
                           "further absent cameras are dropped from the prefix (as upstream); at least one camera "
                           "must be present",
    .weight_files = &weight_files,
    .open_weights = &open_weights,
    .load_normalization = &load_normalization,
    .load = &load_smolvla,
    .export_plan = &export_plan,
};

}  // namespace

const FamilyDescriptor& smolvla_family() { return kSmolVLA; }

}  // namespace tether::models
