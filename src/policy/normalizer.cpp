#include "policy/normalizer.h"

#include <filesystem>
#include <optional>

#include "core/safetensors.h"

namespace tether::policy {

namespace fs = std::filesystem;

const char* norm_mode_name(NormMode m) {
  switch (m) {
    case NormMode::identity: return "IDENTITY";
    case NormMode::mean_std: return "MEAN_STD";
    case NormMode::min_max: return "MIN_MAX";
    case NormMode::quantiles: return "QUANTILES";
    case NormMode::quantile10: return "QUANTILE10";
  }
  return "?";
}

namespace {

NormMode parse_mode(const std::string& s, const std::string& where) {
  for (NormMode m : {NormMode::identity, NormMode::mean_std, NormMode::min_max, NormMode::quantiles,
                     NormMode::quantile10})
    if (s == norm_mode_name(m)) return m;
  throw Error(ErrorCode::unsupported, where + ": normalisation mode '" + s + "' is not supported");
}

std::vector<std::string> required_stats(NormMode m) {
  switch (m) {
    case NormMode::identity: return {};
    case NormMode::mean_std: return {"mean", "std"};
    case NormMode::min_max: return {"min", "max"};
    case NormMode::quantiles: return {"q01", "q99"};
    case NormMode::quantile10: return {"q10", "q90"};
  }
  return {};
}

}  // namespace

Normalizer Normalizer::load(const std::string& dir, const std::string& pipeline_json, const std::string& step_name,
                            const Json& policy_config, std::vector<std::string>& warnings) {
  Normalizer n;
  const fs::path path = fs::path(dir) / pipeline_json;
  Json features = Json::object(), norm_map = policy_config.value("normalization_mapping", Json::object());
  for (const char* group : {"input_features", "output_features"}) {
    const Json part = policy_config.value(group, Json::object());
    for (auto it = part.begin(); it != part.end(); ++it) features[it.key()] = *it;
  }
  std::string state_file;
  std::string where = (fs::path(dir) / "config.json").string();
  if (fs::exists(path)) {
    const Json pipeline = read_json_file(path.string());
    for (const auto& step : pipeline.value("steps", Json::array())) {
      if (step.value("registry_name", "") != step_name) continue;
      where = path.string();
      const Json& cfg = step.value("config", Json::object());
      n.eps_ = json_get_or<float>(cfg, "eps", 1e-8f, where);
      if (cfg.contains("features") && !cfg["features"].empty()) features = cfg["features"];
      if (cfg.contains("norm_map") && !cfg["norm_map"].empty()) norm_map = cfg["norm_map"];
      state_file = step.value("state_file", "");
    }
  }

  SafeTensorsFile* stats_file = nullptr;
  std::optional<SafeTensorsFile> opened;
  if (!state_file.empty() && fs::exists(fs::path(dir) / state_file)) {
    opened = SafeTensorsFile::open((fs::path(dir) / state_file).string());
    stats_file = &*opened;
  }
  for (auto it = features.begin(); it != features.end(); ++it) {
    FeatureNorm f;
    f.type = json_get<std::string>(*it, "type", where + ": features." + it.key());
    auto m = norm_map.find(f.type);
    f.mode = m == norm_map.end() ? NormMode::identity : parse_mode(m->get<std::string>(), where);
    if (stats_file) {
      for (const std::string& name : stats_file->names()) {
        if (name.size() > it.key().size() + 1 && name.compare(0, it.key().size() + 1, it.key() + ".") == 0) {
          const std::string stat = name.substr(it.key().size() + 1);
          if (stat.find('.') == std::string::npos) f.stats[stat] = stats_file->get(name).to_f32();
        }
      }
    }
    const auto req = required_stats(f.mode);
    f.has_stats = !req.empty();
    for (const auto& r : req) f.has_stats = f.has_stats && f.stats.count(r);
    if (!req.empty() && !f.has_stats)
      warnings.push_back(it.key() + ": " + norm_mode_name(f.mode) +
                         " normalisation configured but no stats in the checkpoint; values pass through "
                         "unnormalised, exactly as lerobot does");
    if (f.type == "VISUAL" && f.mode != NormMode::identity && f.has_stats)
      throw Error(ErrorCode::unsupported, where + ": " + it.key() + " uses " + norm_mode_name(f.mode) +
                                              " image normalisation, which is not supported yet");
    n.features_[it.key()] = std::move(f);
  }
  return n;
}

void Normalizer::apply(const std::string& key, float* x, int64_t n, Direction direction) const {
  auto it = features_.find(key);
  if (it == features_.end() || it->second.mode == NormMode::identity || !it->second.has_stats) return;
  const FeatureNorm& f = it->second;
  auto stat = [&](const char* name) -> const std::vector<float>& { return f.stats.at(name); };
  const std::size_t width = stat(required_stats(f.mode)[0].c_str()).size();
  if (width == 0 || n % int64_t(width) != 0)
    throw Error(ErrorCode::invalid_argument, key + ": " + std::to_string(n) + " values do not match the stats width " +
                                                 std::to_string(width));
  // Float32 arithmetic in the same operation order as upstream so results match to the last bit.
  const bool inverse = direction == Direction::unnormalize;
  for (int64_t i = 0; i < n; ++i) {
    const std::size_t j = std::size_t(i) % width;
    float& v = x[i];
    switch (f.mode) {
      case NormMode::mean_std: {
        const float mean = stat("mean")[j], std = stat("std")[j];
        if (direction == Direction::invert_unnormalize) v = std == 0.f ? 0.f : (v - mean) / std;
        else v = inverse ? v * std + mean : (v - mean) / (std + eps_);
        break;
      }
      case NormMode::min_max: {
        const float lo = stat("min")[j];
        float denom = stat("max")[j] - lo;
        if (denom == 0.f) denom = eps_;
        v = inverse ? (v + 1.f) / 2.f * denom + lo : 2.f * (v - lo) / denom - 1.f;
        break;
      }
      case NormMode::quantiles:
      case NormMode::quantile10: {
        const bool q1 = f.mode == NormMode::quantiles;
        const float lo = stat(q1 ? "q01" : "q10")[j];
        float denom = stat(q1 ? "q99" : "q90")[j] - lo;
        if (denom == 0.f) denom = eps_;
        v = inverse ? (v + 1.f) * denom / 2.f + lo : 2.f * (v - lo) / denom - 1.f;
        break;
      }
      case NormMode::identity: break;
    }
  }
}

std::vector<std::string> Normalizer::describe() const {
  std::vector<std::string> out;
  for (const auto& [key, f] : features_)
    out.push_back(key + ": " + norm_mode_name(f.mode) +
                  (f.mode == NormMode::identity ? "" : f.has_stats ? " (stats present)" : " (no stats: identity)"));
  return out;
}

}  // namespace tether::policy
