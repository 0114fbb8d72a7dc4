// What lerobot-saved checkpoints share, whatever the policy family: `type` in config.json, the processor pipelines
// (policy_preprocessor.json / policy_postprocessor.json with their statistics files) that carry the normaliser
// since lerobot 0.4, and the pre-0.4 layout that kept the statistics inside model.safetensors.
// Families saved by lerobot (SmolVLA today, pi0 / pi0.5 next) point their descriptor at these functions.
#pragma once

#include <string>
#include <vector>

#include "core/json_util.h"
#include "models/normalization.h"
#include "models/weights.h"

namespace tether::models::lerobot {

inline constexpr const char* kPreprocessorFile = "policy_preprocessor.json";
inline constexpr const char* kPostprocessorFile = "policy_postprocessor.json";

// config.json's "type" ("" when absent or not a string).
std::string policy_type(const Json& config);

// The normaliser step `step_name` ("normalizer_processor" / "unnormalizer_processor") of the pipeline file
// `pipeline_json` in `dir`. Without the file or the step: config.json's normalization_mapping over its
// input_features + output_features, without statistics.
NormalizationSpec read_pipeline_normalization(const std::string& dir, const std::string& pipeline_json,
                                              const std::string& step_name, const Json& config,
                                              std::vector<std::string>& warnings);

// The statistics of a pre-0.4 checkpoint, converted as lerobot's
// lerobot/processor/migrate_policy_normalization.py converts them:
// - statistics tensors are those whose names start with one of its prefixes (normalize_inputs.buffer_,
//   unnormalize_outputs.buffer_, normalize_targets.buffer_, normalize., unnormalize., ...): the last dotted part
//   is the statistic, the rest the feature key with every '_' read as '.'; a later name (in sorted order) wins;
// - modes come from config.json's normalization_mapping (VISUAL / STATE / ACTION with MEAN_STD / MIN_MAX /
//   IDENTITY; other entries ignored), else from which statistics a feature has; types still without a mode get
//   VISUAL MEAN_STD, STATE MIN_MAX, ACTION MEAN_STD;
// - feature kinds are re-derived from the keys ("image" or "visual" -> VISUAL, "state" -> STATE, "action" ->
//   ACTION, else STATE), as the script rebuilds input_features / output_features;
// - the input step covers input + output features, the output step the output features, eps 1e-8.
struct LegacyStats {
  NormalizationSpec input, output;
  std::vector<std::string> stripped;  // tensors the script removes from the weights
  std::vector<std::string> features;  // feature keys the statistics were found for (as the script names them)
};
// True when `weights` holds statistics tensors the migration script would extract.
bool has_legacy_stats(const TensorStore& weights);
LegacyStats convert_legacy_stats(const Json& config, const TensorStore& weights, const std::string& where);

// lerobot's relative actions (`use_relative_actions`, pi0 / pi0.5 since lerobot 0.6), as the processor pipelines carry
// them: the postprocessor's absolute_actions_processor adds the request's raw state to every unnormalised action
// column, column j to column j, except the columns whose names the preprocessor's relative_actions_processor excludes
// (`exclude_joints`, matched case-insensitively as a whole name or a part of one against `action_names`). Returned as
// runs of converted columns; empty when the postprocessor does not convert. Throws where lerobot would fail at every
// inference (no paired relative step, a state narrower than the action, ...) or would add a normalised state.
std::vector<RelativeAction> read_relative_actions(const std::string& dir, const Json& config,
                                                  std::vector<std::string>& warnings);

// A lerobot checkpoint's normaliser: its processor pipelines when it has them; else, for the pre-0.4 layout, the
// statistics inside the weights (converted as above, the statistics tensors hidden from the model and
// "._orig_mod" removed from names, with a warning saying so); else the config's mapping without statistics.
Normalization load_normalization(const std::string& dir, const Json& config, TensorStore& weights);

// The processor files of `dir` (policy_*.json and policy_*.safetensors), sorted.
std::vector<std::string> processor_files(const std::string& dir);

}  // namespace tether::models::lerobot
