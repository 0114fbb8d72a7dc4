// lerobot's checkpoint conventions: policy type, processor pipelines, and the pre-0.4 statistics conversion.
#include "models/lerobot/checkpoint.h"

#include <algorithm>
#include <filesystem>
#include <optional>

#include "core/error.h"
#include "core/safetensors.h"

namespace tether::models::lerobot {

namespace fs = std::filesystem;

namespace {

// The prefixes migrate_policy_normalization.py extracts statistics from, in its order (first match wins; the
// misspelt one is the script's own).
constexpr const char* kStatPrefixes[] = {
    "normalize_inputs.buffer_", "unnormalize_outputs.buffer_", "normalize_targets.buffer_", "normalize.",
    "unnormalize.",             "input_normalizer.",           "output_normalizer.",        "normalalize_inputs.",
    "unnormalize_outputs.",     "normalize_targets.",          "unnormalize_targets.",
};
// The fragments that make it drop a tensor from the weights (anywhere in the name).
constexpr const char* kStripFragments[] = {
    "normalize_inputs.", "unnormalize_outputs.", "normalize_targets.", "normalize.",
    "unnormalize.",      "input_normalizer.",    "output_normalizer.", "normalizer.",
};
constexpr const char* kCompiledFragment = "._orig_mod";

// (feature, statistic) of a statistics tensor, as the script splits its name.
std::optional<std::pair<std::string, std::string>> stat_of(const std::string& name) {
  for (const char* prefix : kStatPrefixes) {
    const std::string p(prefix);
    if (name.compare(0, p.size(), p) != 0) continue;
    const std::string rest = name.substr(p.size());
    const auto dot = rest.rfind('.');
    if (dot == std::string::npos) return std::nullopt;  // fewer than two parts: skipped
    std::string feature = rest.substr(0, dot);
    std::replace(feature.begin(), feature.end(), '_', '.');
    return std::pair{feature, rest.substr(dot + 1)};
  }
  return std::nullopt;
}

std::string kind_from_key(const std::string& key) {
  if (key.find("image") != std::string::npos || key.find("visual") != std::string::npos) return "VISUAL";
  if (key.find("state") != std::string::npos) return "STATE";
  if (key.find("action") != std::string::npos) return "ACTION";
  return "STATE";
}

}  // namespace

std::string policy_type(const Json& config) {
  const auto it = config.find("type");
  return it != config.end() && it->is_string() ? it->get<std::string>() : std::string();
}

NormalizationSpec read_pipeline_normalization(const std::string& dir, const std::string& pipeline_json,
                                              const std::string& step_name, const Json& config,
                                              std::vector<std::string>& warnings) {
  NormalizationSpec n;
  const fs::path path = fs::path(dir) / pipeline_json;
  Json features = Json::object(), norm_map = config.value("normalization_mapping", Json::object());
  for (const char* group : {"input_features", "output_features"}) {
    const Json part = config.value(group, Json::object());
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
      n.eps = json_get_or<float>(cfg, "eps", 1e-8f, where);
      if (cfg.contains("features") && !cfg["features"].empty()) features = cfg["features"];
      if (cfg.contains("norm_map") && !cfg["norm_map"].empty()) norm_map = cfg["norm_map"];
      state_file = step.value("state_file", "");
    }
  }

  std::optional<SafeTensorsFile> stats_file;
  if (!state_file.empty() && fs::exists(fs::path(dir) / state_file))
    stats_file = SafeTensorsFile::open((fs::path(dir) / state_file).string());
  for (auto it = features.begin(); it != features.end(); ++it) {
    FeatureNorm f;
    f.type = json_get<std::string>(*it, "type", where + ": features." + it.key());
    auto m = norm_map.find(f.type);
    if (m != norm_map.end()) {
      const std::string mode = m->get<std::string>();
      const auto parsed = parse_norm_mode(mode);
      if (!parsed) throw Error(ErrorCode::unsupported, where + ": normalisation mode '" + mode + "' is not supported");
      f.mode = *parsed;
    }
    if (stats_file) {
      for (const std::string& name : stats_file->names()) {
        if (name.size() > it.key().size() + 1 && name.compare(0, it.key().size() + 1, it.key() + ".") == 0) {
          const std::string stat = name.substr(it.key().size() + 1);
          if (stat.find('.') == std::string::npos) f.stats[stat] = stats_file->get(name).to_f32();
        }
      }
    }
    finish_feature(it.key(), f, where, warnings);
    n.features[it.key()] = std::move(f);
  }
  return n;
}

bool has_legacy_stats(const TensorStore& weights) {
  for (const auto& name : weights.names())
    if (stat_of(name)) return true;
  return false;
}

LegacyStats convert_legacy_stats(const Json& config, const TensorStore& weights, const std::string& where) {
  LegacyStats out;
  // Statistics, in the sorted name order the script reads a safetensors file in; a later one replaces an earlier.
  std::map<std::string, std::map<std::string, std::vector<float>>> stats;
  for (const auto& name : weights.names()) {
    if (const auto s = stat_of(name)) stats[s->first][s->second] = weights.get(name).to_f32();
    for (const char* fragment : kStripFragments)
      if (name.find(fragment) != std::string::npos) {
        out.stripped.push_back(name);
        break;
      }
  }
  for (const auto& [feature, _] : stats) out.features.push_back(feature);

  // Features as the script rebuilds them: kind from the key, in the config's order.
  std::vector<std::pair<std::string, std::string>> inputs, outputs;  // key, kind
  for (const auto& [group, into] : {std::pair{"input_features", &inputs}, std::pair{"output_features", &outputs}}) {
    const Json part = config.value(group, Json::object());
    for (auto it = part.begin(); it != part.end(); ++it) into->push_back({it.key(), kind_from_key(it.key())});
  }

  // Modes: the config's mapping (the three kinds and three modes the script knows), else inferred from the
  // statistics of the features it knows, then its defaults.
  std::map<std::string, NormMode> modes;
  if (config.contains("normalization_mapping") && config["normalization_mapping"].is_object()) {
    const Json& mapping = config["normalization_mapping"];
    for (auto it = mapping.begin(); it != mapping.end(); ++it) {
      if (it.key() != "VISUAL" && it.key() != "STATE" && it.key() != "ACTION") continue;
      if (!it->is_string()) continue;
      const std::string mode = it->get<std::string>();
      if (mode == "MEAN_STD") modes[it.key()] = NormMode::mean_std;
      else if (mode == "MIN_MAX") modes[it.key()] = NormMode::min_max;
      else if (mode == "IDENTITY") modes[it.key()] = NormMode::identity;
    }
  }
  if (modes.empty()) {
    // The script's feature list for this inference: config["features"] when present (kind from the key), else
    // one feature per statistics entry, kind from its key (with "pixels" / "joint" / "position" as extra hints).
    std::map<std::string, std::string> known;
    if (config.contains("features") && config["features"].is_object())
      for (auto it = config["features"].begin(); it != config["features"].end(); ++it)
        known[it.key()] = kind_from_key(it.key());
    if (known.empty())
      for (const auto& [key, _] : stats) {
        const bool visual = key.find("image") != std::string::npos || key.find("visual") != std::string::npos ||
                            key.find("pixels") != std::string::npos;
        const bool state = key.find("state") != std::string::npos || key.find("joint") != std::string::npos ||
                           key.find("position") != std::string::npos;
        known[key] = visual ? "VISUAL" : state ? "STATE" : key.find("action") != std::string::npos ? "ACTION" : "STATE";
      }
    for (const auto& [key, s] : stats) {
      const auto k = known.find(key);
      if (k == known.end() || modes.count(k->second)) continue;
      if (s.count("mean") && s.count("std")) modes[k->second] = NormMode::mean_std;
      else if (s.count("min") && s.count("max")) modes[k->second] = NormMode::min_max;
    }
  }
  modes.emplace("VISUAL", NormMode::mean_std);
  modes.emplace("STATE", NormMode::min_max);
  modes.emplace("ACTION", NormMode::mean_std);

  auto feature = [&](const std::string& key, const std::string& kind, std::vector<std::string>& warnings) {
    FeatureNorm f;
    f.type = kind;
    const auto m = modes.find(kind);
    f.mode = m == modes.end() ? NormMode::identity : m->second;
    if (const auto s = stats.find(key); s != stats.end()) f.stats = s->second;
    finish_feature(key, f, where, warnings);
    return f;
  };
  std::vector<std::string> input_warnings, output_warnings;
  for (const auto* group : {&inputs, &outputs})
    for (const auto& [key, kind] : *group) out.input.features[key] = feature(key, kind, input_warnings);
  for (const auto& [key, kind] : outputs) out.output.features[key] = feature(key, kind, output_warnings);
  return out;
}

namespace {

// A pipeline's step by registry name: its position among the steps (-1: absent) and its config.
struct PipelineStep {
  int index = -1;
  Json config = Json::object();
};

PipelineStep find_step(const Json& pipeline, const std::string& registry_name) {
  PipelineStep out;
  const Json steps = pipeline.value("steps", Json::array());
  for (std::size_t i = 0; i < steps.size(); ++i)
    if (steps[i].value("registry_name", "") == registry_name) {
      out.index = int(i);
      out.config = steps[i].value("config", Json::object());
    }
  return out;
}

// Python's str(x).lower() for the names lerobot compares (ASCII letters only: no checkpoint seen names joints
// outside ASCII).
std::string lowered_name(const Json& v) {
  std::string s = v.is_string() ? v.get<std::string>() : v.dump();
  for (char& c : s)
    if (c >= 'A' && c <= 'Z') c = char(c - 'A' + 'a');
  return s;
}

// The width of the `group` feature `key` in config.json (0 when absent); `where` names the file in errors.
int64_t feature_width(const Json& config, const char* group, const std::string& key, const std::string& where) {
  const Json features = config.value(group, Json::object());
  const auto it = features.find(key);
  if (it == features.end()) return 0;
  const auto shape = json_get<std::vector<int64_t>>(*it, "shape", where + ": " + group + "." + key);
  return shape.empty() ? 0 : shape[0];
}

}  // namespace

std::vector<RelativeAction> read_relative_actions(const std::string& dir, const Json& config,
                                                  std::vector<std::string>& warnings) {
  const std::string post_path = (fs::path(dir) / kPostprocessorFile).string();
  const std::string pre_path = (fs::path(dir) / kPreprocessorFile).string();
  const Json post = fs::exists(post_path) ? read_json_file(post_path) : Json::object();
  const Json pre = fs::exists(pre_path) ? read_json_file(pre_path) : Json::object();
  const PipelineStep absolute = find_step(post, "absolute_actions_processor");
  const PipelineStep relative = find_step(pre, "relative_actions_processor");
  const bool converts = absolute.index >= 0 && json_get_or<bool>(absolute.config, "enabled", false, post_path);
  if (!converts) {
    if (relative.index >= 0 && json_get_or<bool>(relative.config, "enabled", false, pre_path))
      warnings.push_back("the checkpoint was trained on actions relative to the state (relative_actions_processor), but "
                         "its postprocessor does not make them absolute: actions are answered as the model predicts "
                         "them, as lerobot does");
    return {};
  }
  if (relative.index < 0)
    throw Error(ErrorCode::format, post_path + ": absolute_actions_processor is enabled but " + kPreprocessorFile +
                                       " has no relative_actions_processor to keep the state (lerobot fails at inference)");
  const PipelineStep normalizer = find_step(pre, "normalizer_processor");
  if (normalizer.index >= 0 && normalizer.index < relative.index)
    throw Error(ErrorCode::unsupported, pre_path + ": relative_actions_processor runs after normalizer_processor, so "
                                        "the state it keeps is normalised; only lerobot's order (raw state) is supported");

  // The step keeps observation.state and adds its first action_dim values.
  const std::string where = (fs::path(dir) / "config.json").string();
  const int64_t action_dim = [&] {
    const Json outputs = config.value("output_features", Json::object());
    for (auto it = outputs.begin(); it != outputs.end(); ++it)
      if (it->value("type", "") == "ACTION") return feature_width(config, "output_features", it.key(), where);
    return int64_t(0);
  }();
  const int64_t state_dim = feature_width(config, "input_features", "observation.state", where);
  if (state_dim == 0)
    throw Error(ErrorCode::unsupported, post_path + ": relative actions are made absolute against observation.state, "
                                        "which " + where + " does not list");
  if (state_dim < action_dim)
    throw Error(ErrorCode::unsupported, post_path + ": relative actions add the state to the action column by column, "
                                        "but the state has " + std::to_string(state_dim) + " values and the action " +
                                        std::to_string(action_dim));

  // Which columns convert: all, unless both exclude_joints and action_names are given (RelativeActionsProcessorStep's
  // mask: a name is excluded when a token equals it or is part of it; columns past the names convert).
  std::vector<bool> converted(std::size_t(action_dim), true);
  const Json exclude = relative.config.value("exclude_joints", Json::array());
  const Json names = relative.config.value("action_names", Json());
  std::vector<std::string> tokens;
  // Python's `if name`: null, false, 0, "" and empty containers are skipped.
  auto truthy = [](const Json& v) {
    if (v.is_null()) return false;
    if (v.is_boolean()) return v.get<bool>();
    if (v.is_number()) return v.get<double>() != 0.0;
    if (v.is_string()) return !v.get<std::string>().empty();
    return !v.empty();
  };
  if (exclude.is_array())
    for (const Json& t : exclude)
      if (truthy(t)) tokens.push_back(lowered_name(t));
  if (!tokens.empty() && names.is_array())
    for (std::size_t j = 0; j < names.size() && j < converted.size(); ++j) {
      const std::string name = lowered_name(names[j]);
      for (const std::string& t : tokens)
        if (name.find(t) != std::string::npos) converted[j] = false;
    }

  std::vector<RelativeAction> out;
  for (int64_t j = 0; j < action_dim;) {
    if (!converted[std::size_t(j)]) {
      ++j;
      continue;
    }
    int64_t end = j;
    while (end < action_dim && converted[std::size_t(end)]) ++end;
    RelativeAction g;
    g.kind = RelativeAction::Kind::joint;
    g.action_offset = g.state_offset = j;
    g.dim = end - j;
    if (names.is_array() && std::size_t(end) <= names.size()) {
      for (int64_t c = j; c < end; ++c) {
        const Json& name = names[std::size_t(c)];
        g.name += (c > j ? ", " : "") + (name.is_string() ? name.get<std::string>() : name.dump());
      }
    } else {
      g.name = "columns " + std::to_string(j) + "-" + std::to_string(end - 1);
    }
    out.push_back(std::move(g));
    j = end;
  }
  return out;
}

Normalization load_normalization(const std::string& dir, const Json& config, TensorStore& weights) {
  Normalization n;
  const bool pipelines =
      fs::exists(fs::path(dir) / kPreprocessorFile) || fs::exists(fs::path(dir) / kPostprocessorFile);
  if (!pipelines && has_legacy_stats(weights)) {
    LegacyStats legacy = convert_legacy_stats(config, weights, weights.label());
    n.input = std::move(legacy.input);
    n.output = std::move(legacy.output);
    for (const auto& name : legacy.stripped) weights.hide(name);
    weights.strip_from_names(kCompiledFragment);
    std::string found;
    for (const auto& f : legacy.features) found += (found.empty() ? "" : ", ") + f;
    n.warnings.push_back("legacy checkpoint (lerobot < 0.4: no processor files, statistics inside " +
                         fs::path(weights.label()).filename().string() + "): statistics for " + found +
                         " converted as lerobot's migrate_policy_normalization does (" +
                         std::to_string(legacy.stripped.size()) + " statistics tensors taken out of the weights)");
    for (const auto* spec : {&n.input, &n.output})
      for (const auto& [key, f] : spec->features)
        if (!required_stats(f.mode).empty() && !f.has_stats) {
          const std::string w = key + ": " + norm_mode_name(f.mode) +
                                " normalisation configured but no stats in the checkpoint; values pass through "
                                "unnormalised, exactly as lerobot does";
          if (std::find(n.warnings.begin(), n.warnings.end(), w) == n.warnings.end()) n.warnings.push_back(w);
        }
    return n;
  }
  std::vector<std::string> post_warnings;
  n.input = read_pipeline_normalization(dir, kPreprocessorFile, "normalizer_processor", config, n.warnings);
  n.output = read_pipeline_normalization(dir, kPostprocessorFile, "unnormalizer_processor", config, post_warnings);
  n.output.relative = read_relative_actions(dir, config, n.warnings);
  // The pre- and post-processor usually carry the same stats; report each missing feature once.
  for (const auto& w : post_warnings)
    if (std::find(n.warnings.begin(), n.warnings.end(), w) == n.warnings.end()) n.warnings.push_back(w);
  return n;
}

std::vector<std::string> processor_files(const std::string& dir) {
  std::vector<std::string> out;
  for (const auto& e : fs::directory_iterator(dir)) {
    const std::string name = e.path().filename().string();
    if (e.is_regular_file() && name.rfind("policy_", 0) == 0 &&
        (name.ends_with(".json") || name.ends_with(".safetensors")))
      out.push_back(name);
  }
  std::sort(out.begin(), out.end());
  return out;
}

}  // namespace tether::models::lerobot
