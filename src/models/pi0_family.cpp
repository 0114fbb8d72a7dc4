// pi0's and pi0.5's family descriptors: lerobot checkpoints of type "pi0" / "pi05" whose PaliGemma tokenizer is named
// by the preprocessor's tokenizer step and found beside the checkpoint or in the hub cache.
#include <filesystem>

#include "models/backbone.h"
#include "models/lerobot/checkpoint.h"
#include "models/pi0.h"

namespace tether::models {

namespace fs = std::filesystem;

namespace {

constexpr const char* kTokenizerRepo = "google/paligemma-3b-pt-224";

std::vector<std::string> weight_files(const fs::path& dir) { return TensorStore::files_in(dir.string()); }

TensorStore open_weights(const fs::path& dir) { return TensorStore::open_dir(dir.string()); }

Normalization load_normalization(const fs::path& dir, const Json& config, TensorStore& weights, const LoadOptions&) {
  return lerobot::load_normalization(dir.string(), config, weights);
}

// The tokenizer repo the preprocessor's tokenizer step names (upstream's default when there is no pipeline file).
std::string tokenizer_name(const fs::path& dir) {
  const fs::path pre = dir / "policy_preprocessor.json";
  if (!fs::exists(pre)) return kTokenizerRepo;
  const Json p = read_json_file(pre.string());
  for (const auto& step : p.value("steps", Json::array()))
    if (step.value("registry_name", "") == "tokenizer_processor")
      return step.value("config", Json::object()).value("tokenizer_name", std::string(kTokenizerRepo));
  return kTokenizerRepo;
}

// Processor files copied; the tokenizer's files travel with the export under the repo id the preprocessor names
// (google/paligemma-3b-pt-224/), which is the first place the loader looks, relative to the checkpoint.
ExportPlan export_plan(const fs::path& dir, const Json& config, const LoadOptions&) {
  ExportPlan plan;
  plan.copy = lerobot::processor_files(dir.string());
  const std::string name = tokenizer_name(dir);
  const fs::path tokenizer = find_backbone_dir(dir, name, "the tokenizer_processor step's tokenizer_name");
  if (fs::path(name).is_absolute())
    throw Error(ErrorCode::unsupported, (dir / "policy_preprocessor.json").string() +
                                            ": an absolute tokenizer_name cannot be exported (name a hub repo)");
  plan.bundles.push_back({tokenizer, name, backbone_files(tokenizer)});
  plan.config = config;
  return plan;
}

constexpr const char* kMissingCamera =
    "an absent camera is replaced by a -1 image that is masked out (as upstream); at least one camera must be present";

// pi0 and pi0.5 differ only in their name, recognition and model class; the files, normalisation and export are
// lerobot's for both.
FamilyDescriptor paligemma_family(const char* name, const char* summary, const char* recognition,
                                  bool (*recognises)(const CheckpointProbe&), decltype(FamilyDescriptor::load) load) {
  return {
      .name = name,
      .summary = summary,
      .recognition = recognition,
      .recognises = recognises,
      .tokenizer = TokenizerKind::sentencepiece,
      .stages = {"preprocess", "vision", "prefix", "denoise"},
      .missing_camera_rule = kMissingCamera,
      .weight_files = &weight_files,
      .open_weights = &open_weights,
      .load_normalization = &load_normalization,
      .load = load,
      .export_plan = &export_plan,
      .keeps_copy = &vlm_keeps_copy,
  };
}

const FamilyDescriptor kPi0 = paligemma_family(
    "pi0",
    "pi0 (lerobot port of openpi): PaliGemma prefix (SigLIP + Gemma 2B), Gemma 300M action expert with a state token, "
    "flow-matching sampler",
    "config.json \"type\": \"pi0\", lerobot",
    [](const CheckpointProbe& p) { return lerobot::policy_type(p.config) == "pi0"; }, &load_pi0);

const FamilyDescriptor kPi05 = paligemma_family(
    "pi05",
    "pi0.5 (lerobot port of openpi): PaliGemma prefix with the discretised state in the prompt, Gemma 300M action "
    "expert with time-conditioned adaptive RMSNorm, flow-matching sampler",
    "config.json \"type\": \"pi05\", lerobot",
    [](const CheckpointProbe& p) { return lerobot::policy_type(p.config) == "pi05"; }, &load_pi05);

}  // namespace

const FamilyDescriptor& pi0_family() { return kPi0; }
const FamilyDescriptor& pi05_family() { return kPi05; }

}  // namespace tether::models
