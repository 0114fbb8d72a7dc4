// Feature normalisation with lerobot's arithmetic (normalizer / unnormalizer processor steps), applied to the
// modes and statistics a family read from its checkpoint (models::NormalizationSpec).
#pragma once

#include <map>
#include <string>
#include <vector>

#include "models/normalization.h"

namespace tether::policy {

using models::FeatureNorm;
using models::norm_mode_name;
using models::NormMode;

class Normalizer {
 public:
  Normalizer() = default;
  explicit Normalizer(models::NormalizationSpec spec)
      : features_(std::move(spec.features)), eps_(spec.eps), relative_(std::move(spec.relative)) {}

  void normalize(const std::string& key, float* x, int64_t n) const { apply(key, x, n, Direction::normalize); }
  void unnormalize(const std::string& key, float* x, int64_t n) const { apply(key, x, n, Direction::unnormalize); }
  // The inverse of unnormalize: maps robot units back to what the model emitted. Differs from normalize only for
  // MEAN_STD, which divides by std + eps; a zero std (every model output maps to the mean) gives 0.
  void invert_unnormalize(const std::string& key, float* x, int64_t n) const {
    apply(key, x, n, Direction::invert_unnormalize);
  }
  // Relative action groups made absolute against the request's raw (robot-unit) state: `actions` holds `rows` rows of
  // `dim` values, after unnormalize. No-op without relative groups.
  void to_absolute(float* actions, int64_t rows, int64_t dim, const std::vector<float>& raw_state) const;
  // The inverse for joint groups: robot-unit actions made relative to `raw_state` (an RTC leftover re-anchored on a new
  // state). An EEF group has no such inverse here: throws.
  void to_relative(float* actions, int64_t rows, int64_t dim, const std::vector<float>& raw_state) const;
  bool has_relative() const { return !relative_.empty(); }
  const std::map<std::string, FeatureNorm>& features() const { return features_; }
  // One line per feature: "observation.state: MEAN_STD (stats present)".
  std::vector<std::string> describe() const;

 private:
  enum class Direction { normalize, unnormalize, invert_unnormalize };
  // x holds n values, a whole number of rows of the feature's width.
  void apply(const std::string& key, float* x, int64_t n, Direction direction) const;
  std::map<std::string, FeatureNorm> features_;
  float eps_ = 1e-8f;
  std::vector<models::RelativeAction> relative_;
};

}  // namespace tether::policy
