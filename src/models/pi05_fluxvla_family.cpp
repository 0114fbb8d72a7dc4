// FluxVLA's pi0.5 (limxdynamics/FluxVLA, PI05FlowMatching) read from its own run directory: what FluxVLA's trainer
// writes (scripts/train.py, fsdp_train_runner.py save_checkpoint) and what its LIBERO evaluation reads
// (libero_eval_runner.py, the eval transforms). Facts below cite FluxVLA at c6cd5a060f52dd083110dda798f3f88e96cf8c42
// as FV:path:line.
#include <algorithm>
#include <cmath>
#include <filesystem>

#include "models/pi05_fluxvla.h"

namespace tether::models {

namespace fs = std::filesystem;

namespace {

constexpr const char* kStatsFile = "dataset_statistics.json";  // FV:fluxvla/datasets/utils/data_utils.py:626-657
constexpr const char* kCheckpoints = "checkpoints";             // FV:fluxvla/engines/runners/fsdp_train_runner.py:200-216

// Prefix renames FluxVLA -> lerobot PI05Policy. FluxVLA's own config maps the same modules onto the openpi/lerobot
// checkpoint it fine-tunes from (name_mapping, FV:configs/pi05/pi05_paligemma_libero_10_full_finetune.py:104-116);
// lerobot adds "model." (PI05Policy.model). Longer prefixes first.
constexpr std::pair<const char*, const char*> kRenames[] = {
    {"vision_backbone.vision.", "model.paligemma_with_expert.paligemma.model.vision_tower."},
    {"projector.projector.", "model.paligemma_with_expert.paligemma.model.multi_modal_projector.linear."},
    {"llm_backbone.", "model.paligemma_with_expert.paligemma.model.language_model."},
    {"llm_expert.", "model.paligemma_with_expert.gemma_expert.model."},
    {"action_in_proj.projector.", "model.action_in_proj."},
    {"action_out_proj.projector.", "model.action_out_proj."},
    {"time_mlp_in.projector.", "model.time_mlp_in."},
    {"time_mlp_out.projector.", "model.time_mlp_out."},
};
// ConditionGemmaModel always builds embed_tokens; the expert only ever gets inputs_embeds
// (FV:fluxvla/models/vlas/pi0_flowmatching.py forward_model), and lerobot deletes the module (modeling_pi05.py:239).
constexpr const char* kDeadExpertEmbedding = "llm_expert.embed_tokens.weight";

bool starts_with(const std::string& s, const std::string& p) { return s.compare(0, p.size(), p) == 0; }

// "step-038064-epoch-24-loss=0.0170.safetensors" -> 38064 (FluxVLA's f'step-{global_step:06d}-epoch-...'); the
// latest-checkpoint.* links and anything else are not step files.
std::optional<long long> step_of(const std::string& name) {
  if (!starts_with(name, "step-") || name.size() < 17 || !name.ends_with(".safetensors")) return std::nullopt;
  std::size_t i = 5;
  while (i < name.size() && std::isdigit(static_cast<unsigned char>(name[i]))) ++i;
  if (i == 5 || i >= name.size() || (name[i] != '-' && name[i] != '.')) return std::nullopt;
  try {
    return std::stoll(name.substr(5, i - 5));
  } catch (const std::exception&) {
    return std::nullopt;
  }
}

// The first object under `root` (depth first, in document order) whose "type" is `type`; null when none.
const Json* find_typed(const Json& root, const std::string& type) {
  if (root.is_object()) {
    if (const auto t = root.find("type"); t != root.end() && t->is_string() && t->get<std::string>() == type)
      return &root;
    for (const auto& [k, v] : root.items())
      if (const Json* f = find_typed(v, type)) return f;
  } else if (root.is_array()) {
    for (const auto& v : root)
      if (const Json* f = find_typed(v, type)) return f;
  }
  return nullptr;
}

const Json& section(const Json& config, const std::string& key) {
  static const Json kNull = nullptr;
  const auto it = config.find(key);
  return it == config.end() ? kNull : *it;
}

std::string where_of(const fs::path& dir, const std::string& field) { return (dir / "config.json").string() + ": " + field; }

void require(bool ok, const fs::path& dir, const std::string& field, const std::string& what) {
  if (!ok) throw Error(ErrorCode::unsupported, where_of(dir, field) + ": " + what + " (Tether runs FluxVLA's pi0.5 as "
                                                                                  "configs/pi05/pi05_paligemma_* set it up)");
}

// A number field compared with the value Tether's pi0.5 implements (absent: FluxVLA's default, which is that value).
void require_value(const Json& obj, const std::string& key, double want, const fs::path& dir, const std::string& path) {
  const double v = json_get_or<double>(obj, key, want, where_of(dir, path));
  require(std::fabs(v - want) <= 1e-12 * std::max(1.0, std::fabs(want)), dir, path + "." + key,
          "is " + std::to_string(v) + ", Tether implements " + std::to_string(want));
}

void require_string(const Json& obj, const std::string& key, const std::string& want, const fs::path& dir,
                    const std::string& path, bool optional = true) {
  const auto it = obj.find(key);
  if (it == obj.end() || it->is_null()) {
    require(optional, dir, path + "." + key, "missing");
    return;
  }
  require(it->is_string() && it->get<std::string>() == want, dir, path + "." + key,
          "is " + it->dump() + ", Tether implements \"" + want + "\"");
}

const Json& model_section(const fs::path& dir, const Json& config) {
  const Json& model = section(config, "model");
  if (!model.is_object()) throw Error(ErrorCode::format, where_of(dir, "model") + ": missing (not a FluxVLA config)");
  return model;
}

// The statistics of the dataset the run was trained on: dataset_statistics.json holds {statistic_name: {key:
// {mean, std, ...}}} (FV:fluxvla/datasets/dataset_wrapper.py:239-405). The evaluation looks up
// f'{task_suite_name}_no_noops' unless norm_stats_key is set (FV:fluxvla/engines/runners/libero_eval_runner.py:141);
// the trainer names it train_dataloader.dataset.statistic_name. A file with one entry needs neither.
std::pair<std::string, Json> dataset_statistics(const fs::path& dir, const Json& config) {
  const fs::path path = dir / kStatsFile;
  if (!fs::exists(path))
    throw Error(ErrorCode::not_found, path.string() + ": missing (FluxVLA's trainer writes it beside checkpoints/ and "
                                                      "its evaluation refuses to run without it)");
  const Json stats = read_json_file(path.string());
  if (!stats.is_object() || stats.empty()) throw Error(ErrorCode::format, path.string() + ": not an object of statistics");
  std::vector<std::string> candidates;
  const Json& eval = section(config, "eval");
  if (eval.is_object()) {
    if (const auto k = eval.find("norm_stats_key"); k != eval.end() && k->is_string()) candidates.push_back(*k);
    if (const auto t = eval.find("task_suite_name"); t != eval.end() && t->is_string())
      candidates.push_back(t->get<std::string>() + "_no_noops");
  }
  if (const Json* ds = find_typed(section(config, "train_dataloader"), "DistributedRepeatingDataset"))
    if (const auto n = ds->find("statistic_name"); n != ds->end() && n->is_string()) candidates.push_back(*n);
  for (const auto& c : candidates)
    if (stats.contains(c)) return {c, stats[c]};
  if (stats.size() == 1) return {stats.begin().key(), stats.begin().value()};
  std::string keys;
  for (const auto& [k, v] : stats.items()) keys += (keys.empty() ? "" : ", ") + k;
  throw Error(ErrorCode::format, path.string() + ": none of the entries the config names (" +
                                     (candidates.empty() ? std::string("none") : candidates.front()) +
                                     ") is in the file, which holds " + keys);
}

std::vector<float> floats(const Json& obj, const std::string& key, const std::string& where) {
  const auto v = json_get<std::vector<double>>(obj, key, where);
  return std::vector<float>(v.begin(), v.end());
}

// mean/std of one key of the statistics, with FluxVLA's optional "mask" (False: the value passes through, which
// mean 0 and std 1 reproduce exactly: x * 1 + 0).
FeatureNorm mean_std_feature(const Json& entry, const std::string& type, std::size_t width, const std::string& where) {
  FeatureNorm f;
  f.type = type;
  f.mode = NormMode::mean_std;
  std::vector<float> mean = floats(entry, "mean", where), std = floats(entry, "std", where);
  if (mean.size() != width || std.size() != width)
    throw Error(ErrorCode::format, where + ": mean/std have " + std::to_string(mean.size()) + "/" +
                                       std::to_string(std.size()) + " values, expected " + std::to_string(width));
  if (const auto m = entry.find("mask"); m != entry.end() && !m->is_null()) {
    const auto mask = json_get<std::vector<bool>>(entry, "mask", where);
    if (mask.size() != width) throw Error(ErrorCode::format, where + ".mask: " + std::to_string(mask.size()) + " values");
    for (std::size_t i = 0; i < width; ++i)
      if (!mask[i]) {
        mean[i] = 0.0f;
        std[i] = 1.0f;
      }
  }
  f.stats["mean"] = std::move(mean);
  f.stats["std"] = std::move(std);
  f.has_stats = true;
  return f;
}

// The eval section's DenormalizeLiberoAction (or another Denormalize* transform), null when absent.
const Json* denormalizer(const Json& config) {
  const Json& eval = section(config, "eval");
  if (!eval.is_object()) return nullptr;
  const auto d = eval.find("denormalize_action");
  return d != eval.end() && d->is_object() ? &*d : nullptr;
}

int64_t action_dim_of(const fs::path& dir, const Json& config, const Json& action_stats) {
  if (const Json* d = denormalizer(config))
    if (const auto a = d->find("action_dim"); a != d->end() && !a->is_null())
      return json_get<int64_t>(*d, "action_dim", where_of(dir, "eval.denormalize_action"));
  return int64_t(json_get<std::vector<double>>(action_stats, "mean", (dir / kStatsFile).string() + ": action").size());
}

// ---------------------------------------------------------------------------------------------------------------
// Descriptor entries

bool recognises(const CheckpointProbe& p) {
  const Json& model = section(p.config, "model");
  if (!model.is_object()) return false;
  const auto t = model.find("type");
  if (t == model.end() || !t->is_string() || t->get<std::string>() != "PI05FlowMatching") return false;
  try {
    return fluxvla_weights_file(p.dir).has_value();
  } catch (const Error&) {
    return true;  // ambiguous steps: the loader says so
  }
}

std::vector<std::string> weight_files(const fs::path& dir) {
  if (auto f = fluxvla_weights_file(dir)) return {*f};
  return {};
}

TensorStore open_weights(const fs::path& dir) {
  const auto file = fluxvla_weights_file(dir);
  if (!file)
    throw Error(ErrorCode::not_found, (dir / kCheckpoints).string() + ": no step-*.safetensors (FluxVLA's weights)");
  TensorStore store = TensorStore::open_file((dir / *file).string());
  for (const std::string& name : store.names()) {
    const auto to = fluxvla_to_lerobot_name(name, store.label());
    if (!to) store.hide(name);
    else store.rename(name, *to);
  }
  return store;
}

Normalization load_normalization(const fs::path& dir, const Json& config, TensorStore&, const LoadOptions&) {
  Normalization n;
  const auto [key, stats] = dataset_statistics(dir, config);
  const std::string where = (dir / kStatsFile).string() + ": " + key;
  // Actions: a[:action_dim] * std + mean (DenormalizeLiberoAction._denormalize, FV:fluxvla/transforms/normalize.py:178-192).
  if (const Json* d = denormalizer(config)) {
    const std::string norm = json_get_or<std::string>(*d, "norm_type", "mean_std", where_of(dir, "eval.denormalize_action"));
    require(norm == "mean_std", dir, "eval.denormalize_action.norm_type", "is \"" + norm + "\"; Tether reads mean_std");
  }
  const Json& action = json_get<Json>(stats, "action", where);
  const int64_t action_dim = action_dim_of(dir, config, action);
  n.output.eps = 1e-6f;
  n.output.features["action"] = mean_std_feature(action, "ACTION", std::size_t(action_dim), where + ".action");
  // The state: (x - mean) / (std + 1e-6) (LiberoProprioFromInputs._normalize, normalize.py:516-531, and the trainer's
  // NormalizeStatesAndActions, normalize.py:418-422): the eps goes in the spec, the arithmetic is the normaliser's.
  n.input.eps = 1e-6f;
  if (const auto p = stats.find("proprio"); p != stats.end() && p->is_object()) {
    const std::size_t width = json_get<std::vector<double>>(*p, "mean", where + ".proprio").size();
    n.input.features["observation.state"] = mean_std_feature(*p, "STATE", width, where + ".proprio");
  }
  n.warnings.push_back("FluxVLA's pi0.5 prompt carries no state and its action expert reads none: the state is "
                       "normalised as FluxVLA does it but does not change the actions");
  if (const Json* d = denormalizer(config);
      d && json_get_or<std::string>(*d, "type", "", where_of(dir, "eval.denormalize_action")) == "DenormalizeLiberoAction" &&
      (json_get_or<bool>(*d, "normalize_gripper_action", true, where_of(dir, "eval.denormalize_action")) ||
       json_get_or<bool>(*d, "invert_gripper_action", true, where_of(dir, "eval.denormalize_action"))))
    n.warnings.push_back("FluxVLA's LIBERO evaluation also maps the last action value g (the gripper) to -sign(2g - 1) "
                         "after unnormalising (DenormalizeLiberoAction); Tether returns the unnormalised value: apply "
                         "that mapping in the client for a LIBERO environment");
  return n;
}

std::unique_ptr<Model> load(const fs::path& dir, const Json& config, TensorStore weights, const LoadOptions& options) {
  FluxvlaModel m = read_fluxvla_model(dir, config);
  return load_pi05_with(dir, m.policy_config, std::move(weights), options, m.options);
}

// FluxVLA's directory as is: the chosen step's weights (converted to the export precision, FluxVLA's names kept so
// FluxVLA can still load it), its config, statistics and tokenizer, and the trainer's other small files.
ExportPlan export_plan(const fs::path& dir, const Json& config, const LoadOptions&) {
  ExportPlan plan;
  plan.copy.push_back(kStatsFile);
  const FluxvlaModel m = read_fluxvla_model(dir, config);
  plan.copy.push_back(fs::relative(m.options.tokenizer_model, dir).generic_string());
  for (const char* f : {"tokenizer/tokenizer_config.json", "config.yaml", "llm_backbone_config.json"})
    if (fs::is_regular_file(dir / f) && std::find(plan.copy.begin(), plan.copy.end(), f) == plan.copy.end())
      plan.copy.push_back(f);
  plan.config = config;
  return plan;
}

// Names are lerobot's here (open_weights renamed them): as for pi0.5, the token embeddings are read a row at a time.
bool keeps_copy(const std::string& tensor) {
  const auto ends_with = [&](const std::string& s) {
    return tensor.size() >= s.size() && tensor.compare(tensor.size() - s.size(), s.size(), s) == 0;
  };
  return !ends_with("embed_tokens.weight") && !ends_with("language_model.norm.weight");
}

const FamilyDescriptor kFluxvla{
    .name = "pi05_fluxvla",
    .summary = "pi0.5 trained with FluxVLA (PI05FlowMatching): lerobot's pi0.5 network read from FluxVLA's run "
               "directory, with FluxVLA's image normalisation, its state-free prompt and its action statistics",
    .recognition = "config.json \"model\": {\"type\": \"PI05FlowMatching\"} with checkpoints/step-*.safetensors, FluxVLA",
    .recognises = &recognises,
    .tokenizer = TokenizerKind::sentencepiece,
    .stages = {"preprocess", "vision", "prefix", "denoise"},
    .missing_camera_rule = "an absent camera is masked out (FluxVLA's img_masks); at least one camera must be present",
    .weight_files = &weight_files,
    .open_weights = &open_weights,
    .load_normalization = &load_normalization,
    .load = &load,
    .export_plan = &export_plan,
    .keeps_copy = &keeps_copy,
};

}  // namespace

const FamilyDescriptor& pi05_fluxvla_family() { return kFluxvla; }

std::optional<std::string> fluxvla_weights_file(const fs::path& dir) {
  const fs::path ckpts = dir / kCheckpoints;
  if (!fs::is_directory(ckpts)) return std::nullopt;
  std::optional<long long> best;
  std::string best_name;
  bool tie = false;
  for (const auto& e : fs::directory_iterator(ckpts)) {
    const std::string name = e.path().filename().string();
    const auto step = step_of(name);
    if (!step || !fs::is_regular_file(e.path())) continue;
    if (!best || *step > *best) {
      best = step;
      best_name = name;
      tie = false;
    } else if (*step == *best) {
      tie = true;
    }
  }
  if (tie)
    throw Error(ErrorCode::format, ckpts.string() + ": more than one weight file for step " + std::to_string(*best) +
                                       " (keep one)");
  if (!best) return std::nullopt;
  return std::string(kCheckpoints) + "/" + best_name;
}

std::optional<std::string> fluxvla_to_lerobot_name(const std::string& name, const std::string& where) {
  if (name == kDeadExpertEmbedding) return std::nullopt;
  for (const auto& [from, to] : kRenames)
    if (starts_with(name, from)) return std::string(to) + name.substr(std::string(from).size());
  throw Error(ErrorCode::format, where + ": tensor '" + name + "' is not a PI05FlowMatching parameter (FluxVLA "
                                         "loads its checkpoints strictly, so its files hold nothing else)");
}

FluxvlaModel read_fluxvla_model(const fs::path& dir, const Json& config) {
  const Json& model = model_section(dir, config);
  require_string(model, "type", "PI05FlowMatching", dir, "model", false);
  const std::string cfg = where_of(dir, "model");
  for (const char* absent : {"state_proj", "action_time_mlp_in", "action_time_mlp_out", "vlm_backbone"})
    require(section(model, absent).is_null(), dir, std::string("model.") + absent, "is set; pi0.5 has none");

  // The VLM (ConditionGemmaModel without adaptive norms) and the expert (with them): FluxVLA builds both from these
  // GemmaConfig fields; Tether takes widths and depths from the tensors and checks the rest.
  const Json& vlm = json_get<Json>(model, "llm_backbone", cfg);
  const Json& expert = json_get<Json>(model, "llm_expert", cfg);
  for (const auto& [part, j] : {std::pair{"model.llm_backbone", &vlm}, std::pair{"model.llm_expert", &expert}}) {
    require_string(*j, "type", "ConditionGemmaModel", dir, part);
    require_value(*j, "rms_norm_eps", 1e-6, dir, part);
    require_value(*j, "rope_theta", 10000.0, dir, part);
    require(section(*j, "rope_scaling").is_null(), dir, std::string(part) + ".rope_scaling", "is set");
    require(!json_get_or<bool>(*j, "attention_bias", false, where_of(dir, part)), dir,
            std::string(part) + ".attention_bias", "is true");
    for (const char* act : {"hidden_activation", "hidden_act"})
      require_string(*j, act, "gelu_pytorch_tanh", dir, part);
  }
  require(section(vlm, "adarms_cond_dim").is_null(), dir, "model.llm_backbone.adarms_cond_dim",
          "is set; the VLM's norms are plain RMSNorms");
  const int64_t expert_width = json_get<int64_t>(expert, "hidden_size", where_of(dir, "model.llm_expert"));
  require(json_get_or<bool>(expert, "use_adarms", false, where_of(dir, "model.llm_expert")), dir,
          "model.llm_expert.use_adarms", "is false; pi0.5's expert norms are adaptive");
  require(json_get_or<int64_t>(expert, "adarms_cond_dim", 0, where_of(dir, "model.llm_expert")) == expert_width, dir,
          "model.llm_expert.adarms_cond_dim", "differs from the expert's hidden_size");
  require(json_get<int64_t>(model, "proj_width", cfg) == expert_width, dir, "model.proj_width",
          "differs from the expert's hidden_size (the time embedding width)");
  for (const char* part : {"projector", "action_in_proj", "action_out_proj", "time_mlp_in", "time_mlp_out"})
    require_string(json_get<Json>(model, part, cfg), "type", "LinearProjector", dir, std::string("model.") + part, false);
  const Json& vision = json_get<Json>(model, "vision_backbone", cfg);
  require_string(vision, "type", "SigLIPViTBackbone", dir, "model.vision_backbone", false);
  require(section(vision, "pretrained_cfg").is_null(), dir, "model.vision_backbone.pretrained_cfg",
          "is set; Tether reads the tower's sizes from vision_config");
  const Json& vcfg = json_get<Json>(vision, "vision_config", where_of(dir, "model.vision_backbone"));
  const std::string vwhere = "model.vision_backbone.vision_config";
  require_value(vcfg, "layer_norm_eps", 1e-6, dir, vwhere);
  require_string(vcfg, "hidden_act", "gelu_pytorch_tanh", dir, vwhere);
  require(!json_get_or<bool>(vcfg, "vision_use_head", false, where_of(dir, vwhere)), dir, vwhere + ".vision_use_head",
          "is true; the image tokens are the last hidden state");
  const int64_t resolution = json_get<int64_t>(vcfg, "image_size", where_of(dir, vwhere));

  // Inference settings. Defaults are PI0FlowMatching.__init__'s (FV:fluxvla/models/vlas/pi0_flowmatching.py:76-111).
  const int64_t chunk = json_get_or<int64_t>(model, "n_action_steps", 50, cfg);
  const int64_t steps = json_get_or<int64_t>(model, "num_steps", 10, cfg);
  const int64_t max_action_dim = json_get_or<int64_t>(model, "max_action_dim", 7, cfg);

  // Preprocessing: the evaluation's transforms (FV:configs/pi05/pi05_paligemma_libero_10_full_finetune.py:186-225),
  // else the trainer's.
  const Json& eval = section(config, "eval");
  const Json& train = section(config, "train_dataloader");
  PiZeroOptions o;
  o.family = &pi05_fluxvla_family();
  o.image_norm = PiZeroOptions::ImageNorm::mean_std_255;
  o.prompt = PiZeroOptions::Prompt::task_newline;
  o.embedding_scale_in_config_dtype = false;  // lang_emb * math.sqrt(dim), FV:pi0_flowmatching.py:237
  o.float32_time = true;                      // FV:pi0_flowmatching.py:642-649 and engines/utils/model_utils.py:40-68
  o.vlm_heads = std::array<int64_t, 2>{json_get<int64_t>(vlm, "num_attention_heads", where_of(dir, "model.llm_backbone")),
                                       json_get<int64_t>(vlm, "num_key_value_heads", where_of(dir, "model.llm_backbone"))};
  o.expert_heads =
      std::array<int64_t, 2>{json_get<int64_t>(expert, "num_attention_heads", where_of(dir, "model.llm_expert")),
                             json_get<int64_t>(expert, "num_key_value_heads", where_of(dir, "model.llm_expert"))};
  o.vision_heads = json_get<int64_t>(vcfg, "num_attention_heads", where_of(dir, vwhere));

  // Images: TransformImage at evaluation ((x - mean) / std on 0..255, float64; FV:fluxvla/transforms/transform_images.py:414-548,
  // defaults 0.5 / 0.5), else the trainer's NormalizeImages (the same means and stds; float32 with std + 1e-8).
  std::vector<std::vector<double>> means, stds;
  if (const Json* t = find_typed(eval, "TransformImage")) {
    means = json_get_or<std::vector<std::vector<double>>>(*t, "means", {{0.5, 0.5, 0.5}}, where_of(dir, "eval TransformImage"));
    stds = json_get_or<std::vector<std::vector<double>>>(*t, "stds", {{0.5, 0.5, 0.5}}, where_of(dir, "eval TransformImage"));
    for (const auto& size : json_get_or<std::vector<std::vector<int64_t>>>(*t, "input_sizes", {}, where_of(dir, "eval TransformImage")))
      require(size.size() == 3 && size[1] == resolution && size[2] == resolution, dir, "eval TransformImage.input_sizes",
              "differs from the vision tower's image_size " + std::to_string(resolution));
  } else if (const Json* t = find_typed(train, "NormalizeImages")) {
    means = json_get<std::vector<std::vector<double>>>(*t, "means", where_of(dir, "NormalizeImages"));
    stds = json_get<std::vector<std::vector<double>>>(*t, "stds", where_of(dir, "NormalizeImages"));
  } else {
    throw Error(ErrorCode::format, where_of(dir, "eval") + ": no TransformImage (nor a NormalizeImages among the "
                                                           "training transforms): the image normalisation is unknown");
  }
  for (const auto* group : {&means, &stds})
    for (const auto& v : *group)
      if (v.size() != 3) throw Error(ErrorCode::format, where_of(dir, "image means/stds") + ": not 3 values per camera");
  for (const auto& v : means) o.image_mean.push_back({v[0], v[1], v[2]});
  for (const auto& v : stds) o.image_std.push_back({v[0], v[1], v[2]});

  // Cameras, in the order the trainer stacked them (ProcessParquetInputs.video_keys), else the evaluation's env keys.
  std::vector<std::string> cameras;
  if (const Json* t = find_typed(train, "ProcessParquetInputs"))
    cameras = json_get_or<std::vector<std::string>>(*t, "video_keys", {}, where_of(dir, "ProcessParquetInputs"));
  if (cameras.empty())
    if (const Json* t = find_typed(eval, "ProcessLiberoEvalInputs"))
      cameras = json_get_or<std::vector<std::string>>(*t, "img_keys", {"agentview_image"}, where_of(dir, "ProcessLiberoEvalInputs"));
  if (cameras.empty())
    throw Error(ErrorCode::format, where_of(dir, "train_dataloader") + ": no ProcessParquetInputs.video_keys nor eval "
                                                                      "ProcessLiberoEvalInputs.img_keys: the cameras are unknown");
  if (o.image_mean.size() != 1 && o.image_mean.size() != cameras.size())
    throw Error(ErrorCode::format, where_of(dir, "image means") + ": " + std::to_string(o.image_mean.size()) +
                                       " entries for " + std::to_string(cameras.size()) + " cameras");

  // Prompt: the task as is (no conversation template), PaligemmaTokenizer.tokenize (FV:fluxvla/tokenizers/paligemma_tokenizer.py:51-71),
  // padded or cut to max_len (LiberoPromptFromInputs, FV:fluxvla/transforms/transform_prompts.py:349-400; default 180).
  int max_len = 180;
  const Json* eval_prompt = find_typed(eval, "LiberoPromptFromInputs");
  const Json* train_prompt = find_typed(train, "ProcessPrompts");
  for (const Json* p : {eval_prompt, train_prompt}) {
    if (!p) continue;
    require(!json_get_or<bool>(*p, "use_conversation", false, where_of(dir, "prompt transform")), dir,
            "LiberoPromptFromInputs.use_conversation", "is true (the OpenVLA-style template)");
    require(!json_get_or<bool>(*p, "with_state", false, where_of(dir, "prompt transform")), dir,
            "ProcessPrompts.with_state", "is true");
    require(section(*p, "negative_prompt").is_null(), dir, "prompt transform.negative_prompt", "is set");
    if (const auto t = p->find("tokenizer"); t != p->end() && t->is_object())
      require_string(*t, "type", "PaligemmaTokenizer", dir, "prompt transform.tokenizer");
  }
  if (const Json* p = find_typed(train, "ParquetPrompter"))
    require(!json_get_or<bool>(*p, "use_conversation", false, where_of(dir, "ParquetPrompter")), dir,
            "ParquetPrompter.use_conversation", "is true (the OpenVLA-style template)");
  require(!find_typed(train, "PreparePromptWithState") && !find_typed(eval, "PreparePromptWithState"), dir,
          "transforms", "use PreparePromptWithState (a prompt with the state)");
  if (eval_prompt) max_len = json_get_or<int>(*eval_prompt, "max_len", 180, where_of(dir, "LiberoPromptFromInputs"));
  else if (train_prompt) max_len = json_get_or<int>(*train_prompt, "max_len", 180, where_of(dir, "ProcessPrompts"));
  o.max_length = max_len;
  // FluxVLA's trainer saves the SentencePiece model it tokenised with into tokenizer/ (PaligemmaTokenizer.save_pretrained,
  // FV:paligemma_tokenizer.py:77-101); the evaluation itself downloads gs://big_vision/paligemma_tokenizer.model.
  for (const char* f : {"tokenizer/tokenizer.model", "tokenizer.model"})
    if (fs::is_regular_file(dir / f)) {
      o.tokenizer_model = dir / f;
      break;
    }
  if (o.tokenizer_model.empty())
    throw Error(ErrorCode::not_found, (dir / "tokenizer" / "tokenizer.model").string() +
                                          ": missing (FluxVLA saves its PaliGemma SentencePiece model there; its "
                                          "evaluation downloads gs://big_vision/paligemma_tokenizer.model)");

  // State: the proprio statistics' width (the model never reads it); padded width from the trainer's transform.
  const auto [stats_key, stats] = dataset_statistics(dir, config);
  int64_t state_dim = 0;
  if (const auto p = stats.find("proprio"); p != stats.end() && p->is_object())
    state_dim = int64_t(json_get<std::vector<double>>(*p, "mean", (dir / kStatsFile).string() + ": proprio").size());
  int64_t max_state_dim = 32;
  if (const Json* t = find_typed(train, "NormalizeStatesAndActions"))
    max_state_dim = json_get_or<int64_t>(*t, "state_dim", 32, where_of(dir, "NormalizeStatesAndActions"));
  max_state_dim = std::max(max_state_dim, state_dim);
  const int64_t action_dim = action_dim_of(dir, config, json_get<Json>(stats, "action", (dir / kStatsFile).string()));

  Json pc = {{"type", "pi05"},
             {"chunk_size", chunk},
             {"n_action_steps", chunk},
             {"num_inference_steps", steps},
             {"max_state_dim", max_state_dim},
             {"max_action_dim", max_action_dim},
             {"image_resolution", {resolution, resolution}},
             {"min_period", 4e-3},  // FV:fluxvla/models/vlas/pi05_flowmatching.py:97-104
             {"max_period", 4.0}};
  Json inputs = Json::object();
  for (const auto& c : cameras) inputs[c] = {{"type", "VISUAL"}, {"shape", {3, resolution, resolution}}};
  inputs["observation.state"] = {{"type", "STATE"}, {"shape", {state_dim}}};
  pc["input_features"] = inputs;
  pc["output_features"] = {{"action", {{"type", "ACTION"}, {"shape", {action_dim}}}}};
  return {pc, o};
}

}  // namespace tether::models
