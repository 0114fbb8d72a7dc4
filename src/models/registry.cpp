// Model family registry: adding a family is one file (or folder) under src/models/ plus one line in kFamilies.
#include <cmath>
#include <filesystem>
#include <random>

#include "core/hash.h"
#include "models/family.h"
#include "models/gr00t.h"
#include "models/pi0.h"
#include "models/pi05_fluxvla.h"
#include "models/smolvla.h"

namespace tether::models {

namespace fs = std::filesystem;

const std::vector<const FamilyDescriptor*>& families() {
  static const std::vector<const FamilyDescriptor*> kFamilies = {
      &smolvla_family(),
      &pi0_family(),
      &pi05_family(),
      &pi05_fluxvla_family(),
      &gr00t_n17_family(),
      &gr00t_n16_family(),
  };
  return kFamilies;
}

std::vector<std::string> model_families() {
  std::vector<std::string> out;
  for (const auto* f : families()) out.push_back(f->name);
  return out;
}

const FamilyDescriptor* find_family(const std::string& name) {
  for (const auto* f : families())
    if (f->name == name) return f;
  return nullptr;
}

const char* tokenizer_kind_name(TokenizerKind k) {
  switch (k) {
    case TokenizerKind::byte_level_bpe: return "byte_level_bpe";
    case TokenizerKind::sentencepiece: return "sentencepiece";
  }
  return "?";
}

void StageTimings::set(const std::string& stage, double value) {
  for (auto& [name, v] : ms)
    if (name == stage) {
      v = value;
      return;
    }
  ms.emplace_back(stage, value);
}

double StageTimings::get(const std::string& stage) const {
  for (const auto& [name, v] : ms)
    if (name == stage) return v;
  return 0;
}

std::optional<std::string> find_camera(const ModelSpec& spec, const std::string& name) {
  for (const auto& c : spec.cameras)
    if (c == name || (!spec.camera_prefix.empty() && c == spec.camera_prefix + name)) return c;
  return std::nullopt;
}

void set_single_groups(ModelSpec& spec) {
  std::string state = spec.state_key.empty() ? "observation.state" : spec.state_key;
  if (state.rfind("observation.", 0) == 0) state = state.substr(12);
  spec.state_groups = {{state.empty() ? "state" : state, spec.state_dim}};
  spec.action_groups = {{spec.action_key.empty() ? "action" : spec.action_key, spec.action_dim}};
}

std::vector<ModalityGroup> state_groups(const ModelSpec& spec) {
  if (!spec.state_groups.empty()) return spec.state_groups;
  ModelSpec single = spec;
  set_single_groups(single);
  return single.state_groups;
}

std::vector<ModalityGroup> action_groups(const ModelSpec& spec) {
  if (!spec.action_groups.empty()) return spec.action_groups;
  ModelSpec single = spec;
  set_single_groups(single);
  return single.action_groups;
}

Json groups_json(const std::vector<ModalityGroup>& groups) {
  Json out = Json::array();
  for (const auto& g : groups) out.push_back({{"name", g.name}, {"dim", g.dim}});
  return out;
}

std::vector<ModalityGroup> answered_action_groups(const ModelSpec& spec, int64_t action_dim) {
  std::vector<ModalityGroup> groups = action_groups(spec);
  if (groups.size() == 1) groups.front().dim = action_dim;
  return groups;
}

CheckpointProbe probe_checkpoint(const fs::path& dir) {
  CheckpointProbe p{dir, Json(nullptr)};
  if (fs::is_regular_file(dir / "config.json")) p.config = read_json_file((dir / "config.json").string());
  return p;
}

const FamilyDescriptor& recognise(const CheckpointProbe& probe) {
  for (const auto* f : families())
    if (f->recognises(probe)) return *f;
  const std::string config_path = (probe.dir / "config.json").string();
  if (probe.config.is_null())
    throw Error(ErrorCode::not_found, config_path + ": missing (not a checkpoint directory?)");
  std::string known;
  for (const auto* f : families()) known += std::string(known.empty() ? "" : "; ") + f->name + " (" + f->recognition + ")";
  // What the checkpoint says it is, in the terms the known conventions use.
  std::string identity = "no \"type\"";
  if (const auto t = probe.config.find("type"); t != probe.config.end()) identity = "model type " + t->dump();
  else if (const auto m = probe.config.find("model_type"); m != probe.config.end()) identity = "model_type " + m->dump();
  throw Error(ErrorCode::unsupported, config_path + ": " + identity + " is not supported; known families: " + known);
}

const FamilyDescriptor& recognise(const fs::path& dir) { return recognise(probe_checkpoint(dir)); }

LoadedCheckpoint load_checkpoint(const fs::path& dir, const LoadOptions& options) {
  if (!fs::is_directory(dir)) throw Error(ErrorCode::not_found, dir.string() + ": not a checkpoint directory");
  CheckpointProbe probe = probe_checkpoint(dir);
  LoadedCheckpoint out;
  out.family = &recognise(probe);
  out.config = std::move(probe.config);
  out.weight_files = out.family->weight_files(dir);
  TensorStore weights = out.family->open_weights(dir);
  out.normalization = out.family->load_normalization(dir, out.config, weights, options);
  out.model = out.family->load(dir, out.config, std::move(weights), options);
  return out;
}

std::string weights_hash(const fs::path& dir, const std::vector<std::string>& weight_files) {
  if (weight_files.size() == 1) return "sha256:" + sha256_file_hex((dir / weight_files[0]).string());
  std::string lines;
  for (const auto& f : weight_files) lines += sha256_file_hex((dir / f).string()) + "  " + f + "\n";
  return "sha256:" + sha256_hex(lines);
}

void seeded_normal(uint64_t seed, float* out, int64_t n) {
  std::mt19937_64 gen(seed);
  auto uniform = [&] { return (double(gen() >> 11) + 0.5) * 0x1.0p-53; };  // in (0, 1), never 0
  constexpr double two_pi = 6.283185307179586476925286766559;
  for (int64_t i = 0; i < n; i += 2) {
    const double r = std::sqrt(-2.0 * std::log(uniform()));
    const double theta = two_pi * uniform();
    out[i] = float(r * std::cos(theta));
    if (i + 1 < n) out[i + 1] = float(r * std::sin(theta));
  }
}

}  // namespace tether::models
