// The family contract: recognition (and its error), sharded weights, and the pre-0.4 statistics conversion.
#include <gtest/gtest.h>

#include <unistd.h>

#include <filesystem>
#include <fstream>

#include "core/error.h"
#include "core/safetensors.h"
#include "models/family.h"
#include "models/lerobot/checkpoint.h"
#include "scratch_dir.h"

using namespace tether;
using namespace tether::models;
namespace fs = std::filesystem;

namespace {

fs::path scratch(const std::string& name) {
  const fs::path d = tether::testing::scratch_dir() / "family" / name;
  fs::remove_all(d);
  fs::create_directories(d);
  return d;
}

void write_json(const fs::path& p, const Json& j) { std::ofstream(p) << j.dump(2); }

Tensor f32(std::vector<float> v) {
  const int64_t n = int64_t(v.size());
  return Tensor::from_f32({n}, std::move(v));
}

// The message and code of what `f` throws.
template <class F>
std::pair<ErrorCode, std::string> error_of(F f) {
  try {
    f();
  } catch (const Error& e) {
    return {e.code(), e.what()};
  }
  return {ErrorCode::internal, ""};
}

}  // namespace

TEST(Families, RegistryKnowsEveryFamily) {
  EXPECT_EQ(model_families(), (std::vector<std::string>{"smolvla", "pi0", "pi05", "pi05_fluxvla", "gr00t_n17", "gr00t_n16"}));
  const FamilyDescriptor* f = find_family("smolvla");
  ASSERT_NE(f, nullptr);
  EXPECT_EQ(f->stages, (std::vector<std::string>{"preprocess", "vision", "prefix", "denoise"}));
  EXPECT_EQ(f->tokenizer, TokenizerKind::byte_level_bpe);
  EXPECT_EQ(find_family("gr00t"), nullptr);
  EXPECT_EQ(&recognise(fs::path(TETHER_FIXTURES_DIR) / "smolvla" / "cam1_stats" / "checkpoint"), f);
  for (const char* name : {"pi0", "pi05"}) {
    const FamilyDescriptor* pi = find_family(name);
    ASSERT_NE(pi, nullptr) << name;
    EXPECT_EQ(pi->tokenizer, TokenizerKind::sentencepiece);
    EXPECT_EQ(&recognise(fs::path(TETHER_FIXTURES_DIR) / name / "cam3_nostats_trunc" / "checkpoint"), pi) << name;
  }
}

TEST(Families, UnknownTypeIsAClearErrorListingTheKnownFamilies) {
  const fs::path d = scratch("unknown");
  write_json(d / "config.json", {{"type", "act"}});
  auto [code, what] = error_of([&] { recognise(d); });
  EXPECT_EQ(code, ErrorCode::unsupported);
  for (const char* part : {"config.json", "model type \"act\"", "not supported", "known families", "smolvla",
                           "\"type\": \"smolvla\""})
    EXPECT_NE(what.find(part), std::string::npos) << part << " in: " << what;
  // A config of another convention (GR00T-style "model_type") is named by what it does say.
  write_json(d / "config.json", {{"model_type", "gr00t_n1_5"}});
  std::tie(code, what) = error_of([&] { recognise(d); });
  EXPECT_EQ(code, ErrorCode::unsupported);
  EXPECT_NE(what.find("model_type \"gr00t_n1_5\""), std::string::npos) << what;
  fs::remove(d / "config.json");
  std::tie(code, what) = error_of([&] { load_checkpoint(d); });
  EXPECT_EQ(code, ErrorCode::not_found);
  EXPECT_NE(what.find("config.json: missing"), std::string::npos) << what;
}

TEST(ShardedWeights, TensorsComeFromTheShardTheIndexNames) {
  const fs::path d = scratch("sharded");
  write_safetensors((d / "model-00001-of-00002.safetensors").string(), {{"a.weight", f32({1, 2})}, {"b.bias", f32({3})}});
  write_safetensors((d / "model-00002-of-00002.safetensors").string(), {{"c.weight", f32({4, 5, 6})}});
  write_json(d / kShardIndexFile, {{"metadata", {{"total_size", 24}}},
                                   {"weight_map",
                                    {{"a.weight", "model-00001-of-00002.safetensors"},
                                     {"b.bias", "model-00001-of-00002.safetensors"},
                                     {"c.weight", "model-00002-of-00002.safetensors"}}}});
  EXPECT_EQ(TensorStore::files_in(d.string()),
            (std::vector<std::string>{kShardIndexFile, "model-00001-of-00002.safetensors",
                                      "model-00002-of-00002.safetensors"}));
  TensorStore s = TensorStore::open_dir(d.string());
  EXPECT_TRUE(s.sharded());
  EXPECT_EQ(s.names(), (std::vector<std::string>{"a.weight", "b.bias", "c.weight"}));
  EXPECT_EQ(s.get("c.weight").to_f32(), (std::vector<float>{4, 5, 6}));
  EXPECT_EQ(fs::path(s.file_of("b.bias")).filename(), "model-00001-of-00002.safetensors");
  EXPECT_EQ(s.paths().size(), 2u);

  Weights w(std::move(s));
  EXPECT_EQ(w.f32("a.weight", {2})[1], 2.0f);
  auto [code, what] = error_of([&] { w.f32("c.weight", {2}); });  // wrong shape: the shard is named
  EXPECT_EQ(code, ErrorCode::format);
  EXPECT_NE(what.find("model-00002-of-00002.safetensors: tensor 'c.weight' has shape [3]"), std::string::npos) << what;
  std::tie(code, what) = error_of([&] { w.f32("d.weight", {1}); });  // not in the map: the index is named
  EXPECT_EQ(code, ErrorCode::not_found);
  EXPECT_NE(what.find(std::string(kShardIndexFile) + ": missing tensor 'd.weight'"), std::string::npos) << what;
}

TEST(ShardedWeights, ErrorsNameTheShard) {
  const fs::path d = scratch("sharded_bad");
  write_safetensors((d / "part-1.safetensors").string(), {{"a", f32({1})}});
  write_json(d / kShardIndexFile, {{"weight_map", {{"a", "part-1.safetensors"}, {"b", "part-1.safetensors"}}}});
  auto [code, what] = error_of([&] { TensorStore::open_dir(d.string()); });
  EXPECT_EQ(code, ErrorCode::format);
  EXPECT_NE(what.find("part-1.safetensors: has no tensor 'b'"), std::string::npos) << what;

  write_json(d / kShardIndexFile, {{"weight_map", {{"a", "part-1.safetensors"}, {"b", "part-2.safetensors"}}}});
  std::tie(code, what) = error_of([&] { TensorStore::open_dir(d.string()); });
  EXPECT_EQ(code, ErrorCode::not_found);
  EXPECT_NE(what.find("shard 'part-2.safetensors'"), std::string::npos) << what;
  EXPECT_NE(what.find("'b'"), std::string::npos) << what;

  write_json(d / kShardIndexFile, {{"weight_map", {{"a", "../elsewhere.safetensors"}}}});
  std::tie(code, what) = error_of([&] { TensorStore::open_dir(d.string()); });
  EXPECT_EQ(code, ErrorCode::format);
  EXPECT_NE(what.find("not a file name inside the checkpoint directory"), std::string::npos) << what;

  write_json(d / kShardIndexFile, {{"metadata", Json::object()}});
  std::tie(code, what) = error_of([&] { TensorStore::open_dir(d.string()); });
  EXPECT_EQ(code, ErrorCode::format);
  EXPECT_NE(what.find("weight_map"), std::string::npos) << what;
}

namespace {

// A pre-0.4 style weights file: a model tensor, statistics buffers, and what the migration script also strips.
TensorStore legacy_store(const fs::path& d) {
  write_safetensors((d / kSingleWeightsFile).string(),
                    {{"model._orig_mod.layer.weight", f32({1, 2})},
                     {"normalize_inputs.buffer_observation_state.mean", f32({1, 2})},
                     {"normalize_inputs.buffer_observation_state.std", f32({3, 4})},
                     {"normalize_inputs.buffer_observation_images_wrist_cam.mean", f32({0.5f})},
                     {"normalize_targets.buffer_action.min", f32({-9, -9})},
                     {"normalize_targets.buffer_action.max", f32({9, 9})},
                     {"unnormalize_outputs.buffer_action.min", f32({-1, -2})},
                     {"unnormalize_outputs.buffer_action.max", f32({1, 2})},
                     {"model.some_normalizer.weight", f32({7})}});
  return TensorStore::open_dir(d.string());
}

Json legacy_config(Json mapping) {
  Json c = {{"type", "smolvla"},
            {"input_features",
             {{"observation.images.wrist_cam", {{"type", "VISUAL"}, {"shape", {3, 8, 8}}}},
              {"observation.state", {{"type", "STATE"}, {"shape", {2}}}},
              {"observation.environment_state", {{"type", "ENV"}, {"shape", {2}}}}}},
            {"output_features", {{"action", {{"type", "ACTION"}, {"shape", {2}}}}}}};
  if (!mapping.is_null()) c["normalization_mapping"] = mapping;
  return c;
}

}  // namespace

TEST(LegacyStats, ConvertedAsTheMigrationScriptDoes) {
  const fs::path d = scratch("legacy");
  TensorStore store = legacy_store(d);
  ASSERT_TRUE(lerobot::has_legacy_stats(store));
  const auto legacy = lerobot::convert_legacy_stats(
      legacy_config({{"VISUAL", "IDENTITY"}, {"STATE", "MEAN_STD"}, {"ACTION", "QUANTILES"}}), store, "w");
  // Feature keys: every '_' read as '.', so the wrist camera's statistics land under another key.
  EXPECT_EQ(legacy.features,
            (std::vector<std::string>{"action", "observation.images.wrist.cam", "observation.state"}));
  const FeatureNorm& state = legacy.input.features.at("observation.state");
  EXPECT_EQ(state.mode, NormMode::mean_std);
  EXPECT_TRUE(state.has_stats);
  EXPECT_EQ(state.stats.at("std"), (std::vector<float>{3, 4}));
  // QUANTILES is not a mode the script reads from the config: ACTION falls back to its default, MEAN_STD, which
  // these min/max statistics do not serve.
  const FeatureNorm& action = legacy.output.features.at("action");
  EXPECT_EQ(action.mode, NormMode::mean_std);
  EXPECT_FALSE(action.has_stats);
  // unnormalize_outputs sorts after normalize_targets: its values win.
  EXPECT_EQ(action.stats.at("min"), (std::vector<float>{-1, -2}));
  // Kinds are re-derived from the keys: the ENV feature becomes STATE.
  EXPECT_EQ(legacy.input.features.at("observation.environment_state").type, "STATE");
  EXPECT_EQ(legacy.input.features.at("observation.images.wrist_cam").mode, NormMode::identity);
  EXPECT_TRUE(legacy.input.features.count("action"));  // the input step covers the outputs too
  EXPECT_FALSE(legacy.output.features.count("observation.state"));
  // Stripped: the statistics and anything whose name contains a normaliser fragment.
  EXPECT_EQ(legacy.stripped.size(), 8u);
  EXPECT_EQ(std::count(legacy.stripped.begin(), legacy.stripped.end(), "model.some_normalizer.weight"), 1);
}

TEST(LegacyStats, ModesInferredWithoutAMappingThenDefaults) {
  const fs::path d = scratch("legacy_infer");
  TensorStore store = legacy_store(d);
  Json config = legacy_config(nullptr);
  config["features"] = {{"observation.state", {{"shape", {2}}}}, {"action", {{"shape", {2}}}}};
  const auto legacy = lerobot::convert_legacy_stats(config, store, "w");
  EXPECT_EQ(legacy.input.features.at("observation.state").mode, NormMode::mean_std);  // from mean/std
  EXPECT_EQ(legacy.output.features.at("action").mode, NormMode::min_max);             // from min/max
  EXPECT_TRUE(legacy.output.features.at("action").has_stats);
  EXPECT_EQ(legacy.input.features.at("observation.images.wrist_cam").mode, NormMode::mean_std);  // VISUAL default
}

TEST(LegacyStats, LoadHidesTheStatisticsAndSaysSo) {
  const fs::path d = scratch("legacy_load");
  TensorStore store = legacy_store(d);
  const Normalization n =
      lerobot::load_normalization(d.string(), legacy_config({{"STATE", "MEAN_STD"}, {"ACTION", "MIN_MAX"}}), store);
  ASSERT_FALSE(n.warnings.empty());
  EXPECT_NE(n.warnings[0].find("legacy checkpoint"), std::string::npos) << n.warnings[0];
  EXPECT_NE(n.warnings[0].find("migrate_policy_normalization"), std::string::npos) << n.warnings[0];
  EXPECT_EQ(store.names(), std::vector<std::string>{"model.layer.weight"});  // stats out, "._orig_mod" removed
  EXPECT_EQ(store.get("model.layer.weight").to_f32(), (std::vector<float>{1, 2}));
  EXPECT_TRUE(n.output.features.at("action").has_stats);

  // With processor files the weights are left alone.
  write_json(d / lerobot::kPreprocessorFile, {{"steps", Json::array()}});
  TensorStore again = TensorStore::open_dir(d.string());
  lerobot::load_normalization(d.string(), legacy_config(nullptr), again);
  EXPECT_EQ(again.names().size(), 9u);
}
