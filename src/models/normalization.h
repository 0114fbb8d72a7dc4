// Feature normalisation as data: per feature its kind, mode and statistics, as a family reads them from its
// checkpoint. The arithmetic that applies them is policy::Normalizer's.
#pragma once

#include <map>
#include <optional>
#include <string>
#include <vector>

namespace tether::models {

// min_max_clipped (GR00T): 2 (x - min) / (max - min) - 1, 0 where max == min, clipped to [-1, 1]; outputs are
// clipped to [-1, 1] before (y + 1) / 2 (max - min) + min. Its min / max are the bounds the checkpoint chose (q01 / q99
// when it uses percentiles).
enum class NormMode { identity, mean_std, min_max, quantiles, quantile10, min_max_clipped };
const char* norm_mode_name(NormMode m);                     // "MEAN_STD", ...
std::optional<NormMode> parse_norm_mode(const std::string& name);
std::vector<std::string> required_stats(NormMode m);        // {"mean", "std"}, ...

struct FeatureNorm {
  std::string type;  // the feature kind as the checkpoint names it: STATE, ACTION, VISUAL, ...
  NormMode mode = NormMode::identity;
  bool has_stats = false;                           // every statistic `mode` needs is present
  std::map<std::string, std::vector<float>> stats;  // "mean", "std", "min", "max", "q01", ...
};

// An action group predicted relative to the robot's current state (GR00T N1.7 with use_relative_action), made
// absolute after unnormalisation against the request's raw state: `joint` adds the state group; `eef_xyz_rot6d`
// composes poses (translation + the first two rows of a rotation matrix), T_abs = T_state * T_action, in float64.
struct RelativeAction {
  enum class Kind { joint, eef_xyz_rot6d } kind = Kind::joint;
  std::string name;  // the action group
  int64_t action_offset = 0, state_offset = 0, dim = 0;  // columns in the action and the state vectors
};

struct NormalizationSpec {
  std::map<std::string, FeatureNorm> features;  // feature key -> how it is (un)normalised
  float eps = 1e-8f;
  std::vector<RelativeAction> relative;  // outputs only: groups made absolute after unnormalising
};

// What a family read: how inputs are normalised and outputs unnormalised, plus sentences for the user.
struct Normalization {
  NormalizationSpec input, output;
  std::vector<std::string> warnings;  // missing statistics, converted legacy statistics, ...
};

// Sets f.has_stats from f.stats and appends a warning for `key` when its mode needs statistics that are absent
// (the values then pass through unchanged, as lerobot does); `where` names the file in errors.
void finish_feature(const std::string& key, FeatureNorm& f, const std::string& where,
                    std::vector<std::string>& warnings);

}  // namespace tether::models
