// Normalisation modes, their statistics, and the missing-statistics rule every family shares.
#include "models/normalization.h"

#include "core/error.h"

namespace tether::models {

const char* norm_mode_name(NormMode m) {
  switch (m) {
    case NormMode::identity: return "IDENTITY";
    case NormMode::mean_std: return "MEAN_STD";
    case NormMode::min_max: return "MIN_MAX";
    case NormMode::quantiles: return "QUANTILES";
    case NormMode::quantile10: return "QUANTILE10";
    case NormMode::min_max_clipped: return "MIN_MAX_CLIPPED";
  }
  return "?";
}

std::optional<NormMode> parse_norm_mode(const std::string& name) {
  for (NormMode m : {NormMode::identity, NormMode::mean_std, NormMode::min_max, NormMode::quantiles,
                     NormMode::quantile10, NormMode::min_max_clipped})
    if (name == norm_mode_name(m)) return m;
  return std::nullopt;
}

std::vector<std::string> required_stats(NormMode m) {
  switch (m) {
    case NormMode::identity: return {};
    case NormMode::mean_std: return {"mean", "std"};
    case NormMode::min_max:
    case NormMode::min_max_clipped: return {"min", "max"};
    case NormMode::quantiles: return {"q01", "q99"};
    case NormMode::quantile10: return {"q10", "q90"};
  }
  return {};
}

void finish_feature(const std::string& key, FeatureNorm& f, const std::string& where,
                    std::vector<std::string>& warnings) {
  const auto req = required_stats(f.mode);
  f.has_stats = !req.empty();
  for (const auto& r : req) f.has_stats = f.has_stats && f.stats.count(r);
  if (!req.empty() && !f.has_stats)
    warnings.push_back(key + ": " + norm_mode_name(f.mode) +
                       " normalisation configured but no stats in the checkpoint; values pass through "
                       "unnormalised, exactly as lerobot does");
  if (f.type == "VISUAL" && f.mode != NormMode::identity && f.has_stats)
    throw Error(ErrorCode::unsupported, where + ": " + key + " uses " + norm_mode_name(f.mode) +
                                            " image normalisation, which is not supported yet");
}

}  // namespace tether::models
