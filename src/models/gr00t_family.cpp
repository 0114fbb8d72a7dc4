// GR00T N1.7's and N1.6's family descriptors: raw NVIDIA checkpoints (config.json model_type "Gr00tN1d7" /
// "Gr00tN1d6", sharded safetensors, processor_config.json, statistics.json, embodiment_id.json) whose backbone files
// (N1.7: the Qwen3-VL repository; N1.6: the Eagle directory) are found by the config's model_name beside the
// checkpoint or in the hub cache.
#include <filesystem>

#include "models/backbone.h"
#include "models/gr00t.h"

namespace tether::models {

namespace fs = std::filesystem;

namespace {

constexpr const char* kSidecars[] = {"processor_config.json", "statistics.json", "embodiment_id.json"};

bool is_model_type(const CheckpointProbe& p, const char* type) {
  if (!p.config.is_object() || p.config.contains("type")) return false;  // "type" marks a lerobot checkpoint
  return p.config.value("model_type", std::string()) == type;
}
bool recognises_n17(const CheckpointProbe& p) { return is_model_type(p, "Gr00tN1d7"); }
bool recognises_n16(const CheckpointProbe& p) { return is_model_type(p, "Gr00tN1d6"); }

std::vector<std::string> weight_files(const fs::path& dir) { return TensorStore::files_in(dir.string()); }

TensorStore open_weights(const fs::path& dir) { return TensorStore::open_dir(dir.string()); }

// The served embodiment's bounds, min-max and clipped as lerobot's N1.7 pack and decode steps (and Isaac-GR00T's
// StateActionProcessor for N1.6's actions) apply them. N1.6 encodes its state itself (sin/cos, mean/std or min/max
// per group: the model file), so only N1.7 normalises the state here.
Normalization gr00t_normalization(const fs::path& dir, const Json& config, const LoadOptions& options, bool state) {
  Gr00tEmbodiment e = read_gr00t_embodiment(dir, options.embodiment);
  // Per-step bounds (relative groups' statistics) for the rows a chunk keeps: min(model horizon, the embodiment's).
  if (e.action_bound_rows > 1) {
    const int64_t horizon = json_get_or<int64_t>(config, "action_horizon", 40, (dir / "config.json").string());
    const int64_t rows = std::min(e.action_bound_rows, horizon), dim = int64_t(e.action_lo.size()) / e.action_bound_rows;
    e.action_lo.resize(std::size_t(rows * dim));
    e.action_hi.resize(std::size_t(rows * dim));
  }
  const std::string stats = gr00t_sidecar(dir, "statistics.json").string();
  Normalization n;
  if (state) {
    FeatureNorm f{"STATE", NormMode::min_max_clipped, false, {{"min", e.state_lo}, {"max", e.state_hi}}};
    finish_feature("state", f, stats, n.warnings);
    n.input.features["state"] = f;
  }
  FeatureNorm action{"ACTION", NormMode::min_max_clipped, false, {{"min", e.action_lo}, {"max", e.action_hi}}};
  if (!e.action_mean_std.empty()) {  // N1.6's mean/std action groups, one row repeated as the bounds' rows are
    const std::size_t rows = e.action_lo.size() / e.action_mean_std.size();
    for (const auto& [name, row] : {std::pair{"mean_std_mask", &e.action_mean_std}, std::pair{"mean", &e.action_mean},
                                    std::pair{"std", &e.action_std}}) {
      std::vector<float>& v = action.stats[name];
      for (std::size_t r = 0; r < rows; ++r) v.insert(v.end(), row->begin(), row->end());
    }
  }
  finish_feature("action", action, stats, n.warnings);
  n.output.features["action"] = action;
  n.output.relative = e.relative;
  return n;
}

Normalization load_normalization_n17(const fs::path& dir, const Json& config, TensorStore&, const LoadOptions& options) {
  return gr00t_normalization(dir, config, options, true);
}

Normalization load_normalization_n16(const fs::path& dir, const Json& config, TensorStore&, const LoadOptions& options) {
  return gr00t_normalization(dir, config, options, false);
}

// The sidecar files are copied, or, when one embodiment is exported, written narrowed to it (its modality config,
// statistics and weights row), so that the export loads without naming it; the weights keep every row. The backbone
// repository's files travel under the id the config names, which the loader looks for relative to the checkpoint first.
ExportPlan export_plan(const fs::path& dir, const Json& config, const LoadOptions& options,
                       const std::string& default_backbone) {
  ExportPlan plan;
  // Lexically: hub snapshots are symlinks into the blob store, which fs::relative would follow.
  if (options.embodiment.empty()) {
    for (const char* f : kSidecars) plan.copy.push_back(gr00t_sidecar(dir, f).lexically_relative(dir).string());
  } else {
    const Gr00tEmbodiment e = read_gr00t_embodiment(dir, options.embodiment);  // an unknown tag lists the known ones
    auto sidecar = [&](const char* name) { return gr00t_sidecar(dir, name).lexically_relative(dir).string(); };
    Json processor = read_json_file(gr00t_sidecar(dir, "processor_config.json").string());
    Json& modalities = processor.at("processor_kwargs").at("modality_configs");
    modalities = Json{{e.tag, modalities.at(e.tag)}};
    const Json stats = read_json_file(gr00t_sidecar(dir, "statistics.json").string());
    plan.written.push_back({sidecar("processor_config.json"), processor});
    plan.written.push_back({sidecar("statistics.json"), Json{{e.tag, stats.at(e.tag)}}});
    plan.written.push_back({sidecar("embodiment_id.json"), Json{{e.tag, e.id}}});
  }
  const std::string name = config.value("model_name", default_backbone);
  if (fs::path(name).is_absolute())
    throw Error(ErrorCode::unsupported, (dir / "config.json").string() +
                                            ": an absolute model_name cannot be exported (name a hub repo)");
  const fs::path backbone = find_backbone_dir(dir, name, "model_name in config.json");
  plan.bundles.push_back({backbone, name, backbone_files(backbone)});
  plan.config = config;
  return plan;
}

ExportPlan export_plan_n17(const fs::path& dir, const Json& config, const LoadOptions& options) {
  return export_plan(dir, config, options, "nvidia/Cosmos-Reason2-2B");
}
ExportPlan export_plan_n16(const fs::path& dir, const Json& config, const LoadOptions& options) {
  return export_plan(dir, config, options, "nvidia/Eagle-Block2A-2B-v2");
}

const FamilyDescriptor kGr00tN17 = {
    .name = "gr00t_n17",
    .summary = "GR00T N1.7 (NVIDIA): Qwen3-VL backbone (Cosmos-Reason2) cut at select_layer, VL self-attention, "
               "alternating cross/self-attention DiT with per-embodiment encoders, 4-step flow matching",
    .recognition = "config.json \"model_type\": \"Gr00tN1d7\" (raw NVIDIA layout)",
    .recognises = &recognises_n17,
    .tokenizer = TokenizerKind::byte_level_bpe,
    .stages = {"preprocess", "vision", "backbone", "denoise"},
    .missing_camera_rule = "every camera of the embodiment is required (upstream has no rule for a missing one)",
    .weight_files = &weight_files,
    .open_weights = &open_weights,
    .load_normalization = &load_normalization_n17,
    .load = &load_gr00t_n17,
    .export_plan = &export_plan_n17,
    .keeps_copy = &vlm_keeps_copy,
};

const FamilyDescriptor kGr00tN16 = {
    .name = "gr00t_n16",
    .summary = "GR00T N1.6 (NVIDIA): Eagle backbone (SigLIP2, pixel unshuffle + mlp1, Qwen3 cut at select_layer), "
               "alternating cross/self-attention DiT with per-embodiment encoders, 4-step flow matching",
    .recognition = "config.json \"model_type\": \"Gr00tN1d6\" (raw NVIDIA layout)",
    .recognises = &recognises_n16,
    .tokenizer = TokenizerKind::byte_level_bpe,
    .stages = {"preprocess", "vision", "backbone", "denoise"},
    .missing_camera_rule = "every camera of the embodiment is required (upstream has no rule for a missing one)",
    .weight_files = &weight_files,
    .open_weights = &open_weights,
    .load_normalization = &load_normalization_n16,
    .load = &load_gr00t_n16,
    .export_plan = &export_plan_n16,
    .keeps_copy = &vlm_keeps_copy,
};

}  // namespace

const FamilyDescriptor& gr00t_n17_family() { return kGr00tN17; }
const FamilyDescriptor& gr00t_n16_family() { return kGr00tN16; }

}  // namespace tether::models
