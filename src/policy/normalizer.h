// Feature normalisation exactly as lerobot's normalizer/unnormalizer processor steps do it, read from the
// checkpoint's processor pipeline JSON and its stats safetensors.
#pragma once

#include <map>
#include <string>
#include <vector>

#include "core/json_util.h"

namespace tether::policy {

enum class NormMode { identity, mean_std, min_max, quantiles, quantile10 };
const char* norm_mode_name(NormMode m);

struct FeatureNorm {
  std::string type;  // lerobot FeatureType: STATE, ACTION, VISUAL, ...
  NormMode mode = NormMode::identity;
  bool has_stats = false;
  std::map<std::string, std::vector<float>> stats;  // "mean", "std", "min", "max", "q01", ...
};

class Normalizer {
 public:
  // Reads the step named `step_name` ("normalizer_processor" or "unnormalizer_processor") from the pipeline file
  // `pipeline_json` in `dir`. Without the file or the step, falls back to config.json's normalization_mapping with
  // no stats. Features whose mode needs stats that are missing are left unchanged, as upstream does; a warning
  // naming them is appended to `warnings`.
  static Normalizer load(const std::string& dir, const std::string& pipeline_json, const std::string& step_name,
                         const Json& policy_config, std::vector<std::string>& warnings);

  void normalize(const std::string& key, float* x, int64_t n) const { apply(key, x, n, Direction::normalize); }
  void unnormalize(const std::string& key, float* x, int64_t n) const { apply(key, x, n, Direction::unnormalize); }
  // The inverse of unnormalize: maps robot units back to what the model emitted. Differs from normalize only for
  // MEAN_STD, which divides by std + eps; a zero std (every model output maps to the mean) gives 0.
  void invert_unnormalize(const std::string& key, float* x, int64_t n) const {
    apply(key, x, n, Direction::invert_unnormalize);
  }
  const std::map<std::string, FeatureNorm>& features() const { return features_; }
  // One line per feature: "observation.state: MEAN_STD (stats present)".
  std::vector<std::string> describe() const;

 private:
  enum class Direction { normalize, unnormalize, invert_unnormalize };
  // x holds n values, a whole number of rows of the feature's width.
  void apply(const std::string& key, float* x, int64_t n, Direction direction) const;
  std::map<std::string, FeatureNorm> features_;
  float eps_ = 1e-8f;
};

}  // namespace tether::policy
