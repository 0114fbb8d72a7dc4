// FluxVLA's pi0.5 run directories: the weight mapping (bit for bit the lerobot fixture's network), the tokenizer
// route (libsentencepiece's ids), the layout rules (newest step, statistics entry, mask), and the refusals.
#include <gtest/gtest.h>

#include <unistd.h>

#include <cstring>
#include <filesystem>
#include <fstream>

#include "core/safetensors.h"
#include "models/pi05_fluxvla.h"
#include "policy/policy.h"
#include "scratch_dir.h"

using namespace tether;
using namespace tether::models;
namespace fs = std::filesystem;

namespace {

const fs::path kRoot = fs::path(TETHER_FIXTURES_DIR) / "pi05_fluxvla";

struct Captured {
  Shape shape;
  std::vector<float> values;
};

fs::path scratch(const std::string& name) {
  const fs::path d = tether::testing::scratch_dir() / "fluxvla" / name;
  fs::remove_all(d);
  fs::create_directories(d.parent_path());
  return d;
}

fs::path copy_case(const std::string& c, const std::string& name) {
  const fs::path d = scratch(name);
  fs::copy(kRoot / c / "checkpoint", d, fs::copy_options::recursive);
  return d;
}

void write_json(const fs::path& p, const Json& j) { std::ofstream(p, std::ios::trunc) << j.dump(2); }

template <class F>
std::pair<ErrorCode, std::string> error_of(F f) {
  try {
    f();
  } catch (const Error& e) {
    return {e.code(), e.what()};
  }
  return {ErrorCode::internal, ""};
}

// The oracle's batch as the model sees it (the state already normalised: it does not matter here).
std::vector<ModelInput> oracle_batch(const std::string& c, const ModelSpec& spec) {
  const SafeTensorsFile oracle = SafeTensorsFile::open((kRoot / c / "oracle.safetensors").string());
  const Json cameras = Json::parse(oracle.metadata().at("cameras"));
  const Json instructions = Json::parse(oracle.metadata().at("instructions"));
  const Json files = Json::parse(oracle.metadata().at("input_files"));
  const Tensor state = oracle.get("input.state");
  const std::vector<float> states = state.to_f32(), noise = oracle.get("input.noise").to_f32();
  std::vector<ModelInput> batch(std::size_t(state.dim(0)));
  const int64_t n = spec.chunk_size * spec.max_action_dim;
  for (std::size_t b = 0; b < batch.size(); ++b) {
    batch[b].state.assign(states.begin() + int64_t(b) * state.dim(1), states.begin() + int64_t(b + 1) * state.dim(1));
    batch[b].instruction = instructions.at(b).get<std::string>();
    batch[b].noise.assign(noise.begin() + int64_t(b) * n, noise.begin() + int64_t(b + 1) * n);
    for (std::size_t i = 0; i < cameras.size(); ++i) {
      const std::string key = cameras[i].get<std::string>();
      // The model's camera of the same position (the lerobot checkpoint is fed under the FluxVLA names too).
      batch[b].images[spec.cameras.at(i)] =
          vision::load_image((kRoot / c / "inputs" / files.at(key).at(b).get<std::string>()).string());
    }
  }
  return batch;
}

std::map<std::string, Captured> run(Model& m, const std::vector<ModelInput>& batch, ModelOutput* out = nullptr) {
  std::map<std::string, Captured> captured;
  m.set_debug_hook([&](const std::string& n, const Tensor& t) { captured[n] = {t.shape, t.to_f32()}; });
  ModelOutput o = m.predict(batch);
  captured["out.actions_normalized"] = {{o.batch, o.chunk_size, o.action_dim}, o.actions};
  if (out) *out = std::move(o);
  return captured;
}

class FluxvlaCase : public ::testing::TestWithParam<std::string> {};

}  // namespace

// (a) The weight mapping: the FluxVLA directory through its family, and the lerobot checkpoint its tensors came
// from through load_pi05_with with the same feeding options, give the same bits everywhere.
TEST_P(FluxvlaCase, SameNetworkAsTheLerobotCheckpointBitForBit) {
  const std::string c = GetParam();
  const fs::path flux = kRoot / c / "checkpoint";
  const SafeTensorsFile oracle = SafeTensorsFile::open((kRoot / c / "oracle.safetensors").string());
  const fs::path lerobot = fs::path(TETHER_FIXTURES_DIR) / oracle.metadata().at("source_checkpoint");
  for (const cpu::Precision precision : {cpu::Precision::fp32, cpu::Precision::bf16}) {
    LoadOptions options;
    options.precision = precision;
    LoadedCheckpoint a = load_checkpoint(flux, options);
    ASSERT_EQ(a.family, &pi05_fluxvla_family());
    EXPECT_EQ(a.weight_files, std::vector<std::string>{oracle.metadata().at("weights_file")});
    const FluxvlaModel m = read_fluxvla_model(flux, a.config);
    auto b = load_pi05_with(lerobot, m.policy_config, TensorStore::open_dir(lerobot.string()), options, m.options);
    const auto batch = oracle_batch(c, a.model->spec());
    const auto got = run(*a.model, batch), want = run(*b, batch);
    ASSERT_EQ(got.size(), want.size());
    int compared = 0;
    for (const auto& [name, w] : want) {
      ASSERT_TRUE(got.count(name)) << name;
      const Captured& g = got.at(name);
      ASSERT_EQ(g.shape, w.shape) << name;
      EXPECT_EQ(std::memcmp(g.values.data(), w.values.data(), w.values.size() * sizeof(float)), 0)
          << name << " (" << cpu::precision_name(precision) << ") differs";
      ++compared;
    }
    std::printf("  [%s, %s] %d tensors identical (max |diff| 0), incl. mid.vision.*, mid.prefix_k/v.*, "
                "mid.velocity.step0, out.actions_normalized\n",
                c.c_str(), cpu::precision_name(precision), compared);
    for (const char* must : {"mid.prefix_embs", "mid.prefix_k.0", "mid.prefix_v.0", "mid.velocity.step0",
                             "mid.adarms_cond.step0", "out.actions_normalized"})
      EXPECT_TRUE(want.count(must)) << must;
  }
}

// FluxVLA's LIBERO client turns the gripper value into -sign(2g - 1) after unnormalising; Tether leaves that to the
// client (a load warning says so): applied to Tether's robot-unit actions it gives the oracle's env actions.
TEST_P(FluxvlaCase, LiberoGripperMappingIsTheClientsStep) {
  const std::string c = GetParam();
  auto p = policy::Policy::load((kRoot / c / "checkpoint").string());
  bool warned = false;
  for (const auto& w : p->load_warnings()) warned = warned || w.find("-sign(2g - 1)") != std::string::npos;
  EXPECT_TRUE(warned);
  const auto inputs = oracle_batch(c, p->spec());
  std::vector<policy::Observation> batch(inputs.size());
  const SafeTensorsFile oracle = SafeTensorsFile::open((kRoot / c / "oracle.safetensors").string());
  const std::vector<float> states = oracle.get("input.state").to_f32();
  for (std::size_t b = 0; b < inputs.size(); ++b) {
    batch[b].images = inputs[b].images;
    batch[b].instruction = inputs[b].instruction;
    batch[b].noise = inputs[b].noise;
    batch[b].state.assign(states.begin() + int64_t(b) * p->spec().state_dim,
                          states.begin() + int64_t(b + 1) * p->spec().state_dim);
  }
  const auto pred = p->predict(batch);
  const std::vector<float> want = oracle.get("out.actions_libero").to_f32();
  std::vector<float> got;
  for (const auto& item : pred.items)
    for (int64_t r = 0; r < item.chunk_size; ++r)
      for (int64_t j = 0; j < item.action_dim; ++j) {
        const float v = item.actions[std::size_t(r * item.action_dim + j)];
        got.push_back(j + 1 < item.action_dim ? v : -(2 * v - 1 > 0 ? 1.f : 2 * v - 1 < 0 ? -1.f : 0.f));
      }
  ASSERT_EQ(got.size(), want.size());
  double worst = 0;
  for (std::size_t i = 0; i < got.size(); ++i) worst = std::max(worst, double(std::fabs(got[i] - want[i])));
  EXPECT_LE(worst, 1e-5);
}

INSTANTIATE_TEST_SUITE_P(Fixtures, FluxvlaCase, ::testing::Values("libero_f32", "variant_bf16"));

// (c) The tokenizer.model route: FluxVLA runs libsentencepiece itself (PaligemmaTokenizer.tokenize), with add_bos
// explicit; Tether converts the same file as GemmaTokenizer (whose add_bos_token defaults to false) and adds BOS
// itself. The ids equal libsentencepiece's for every string that does not write a special token.
TEST(FluxvlaTokenizer, PromptIdsAreLibsentencepieces) {
  const Json doc = read_json_file((kRoot / "tokenizer_cases.json").string());
  const fs::path model = kRoot / "libero_f32" / "checkpoint" / "tokenizer" / "tokenizer.model";
  const text::PretrainedTokenizer tok = text::load_gemma_sentencepiece(model.string());
  ASSERT_TRUE(tok.bos_token_id.has_value());
  EXPECT_EQ(*tok.bos_token_id, doc.at("bos_id").get<int32_t>());
  // The bare model adds nothing by itself, as transformers' GemmaTokenizer without add_bos_token: the prompt's BOS
  // is the family's.
  EXPECT_EQ(tok.tokenizer.encode("pick", true), tok.tokenizer.encode("pick", false));
  int same = 0, special = 0;
  for (const auto& c : doc.at("cases")) {
    const std::string text = c.at("text");
    const TaskPrompt p = task_newline_prompt(tok, text, 0);
    const TaskPrompt cut = task_newline_prompt(tok, text, 180);
    const auto want = c.at("ids").get<std::vector<int32_t>>();
    const auto want_cut = c.at("ids_max_len_180").get<std::vector<int32_t>>();
    if (c.at("writes_special").get<bool>()) {
      EXPECT_TRUE(p.wrote_special) << text;
      EXPECT_NE(p.ids, want) << text << ": expected to differ (SentencePiece spells special tokens out)";
      ++special;
      continue;
    }
    EXPECT_FALSE(p.wrote_special) << text;
    EXPECT_EQ(p.ids, want) << text;
    EXPECT_EQ(cut.ids, want_cut) << text;
    same += p.ids == want;
  }
  std::printf("  %d strings: ids equal libsentencepiece's; %d strings writing special tokens differ (and warn)\n", same,
              special);
  EXPECT_GE(same, 15);
  // FluxVLA's own tokenizer_config.json names its wrapper class, which the transformers route refuses.
  auto [code, what] = error_of([&] { text::load_pretrained_tokenizer(model.parent_path().string()); });
  EXPECT_EQ(code, ErrorCode::unsupported) << what;
}

TEST(FluxvlaLayout, RecognisedAndTheNewestStepIsRead) {
  EXPECT_EQ(&recognise(kRoot / "libero_f32" / "checkpoint"), &pi05_fluxvla_family());
  EXPECT_NE(&recognise(fs::path(TETHER_FIXTURES_DIR) / "pi05" / "cam2_bf16" / "checkpoint"), &pi05_fluxvla_family());
  const fs::path d = copy_case("libero_f32", "steps");
  EXPECT_EQ(fluxvla_weights_file(d), "checkpoints/step-000120-epoch-03-loss=0.0170.safetensors");
  // Not step files: the trainer's latest-checkpoint link, its .pt files, other names.
  fs::copy_file(d / "checkpoints" / "step-000040-epoch-01-loss=0.5000.safetensors", d / "checkpoints" / "latest-checkpoint.safetensors");
  std::ofstream(d / "checkpoints" / "step-000900-epoch-09-loss=0.0100.pt") << "x";
  std::ofstream(d / "checkpoints" / "step-x.safetensors") << "x";
  EXPECT_EQ(fluxvla_weights_file(d), "checkpoints/step-000120-epoch-03-loss=0.0170.safetensors");
  // A step file that is a link counts (a Hugging Face snapshot links every file into its blobs).
  fs::create_symlink("step-000120-epoch-03-loss=0.0170.safetensors", d / "checkpoints" / "step-000950-epoch-09-loss=0.1.safetensors");
  EXPECT_EQ(fluxvla_weights_file(d), "checkpoints/step-000950-epoch-09-loss=0.1.safetensors");
  // A later step wins; two files of one step are an error.
  fs::copy_file(d / "checkpoints" / "step-000120-epoch-03-loss=0.0170.safetensors",
                d / "checkpoints" / "step-001000-epoch-24-loss=0.0100.safetensors");
  EXPECT_EQ(fluxvla_weights_file(d), "checkpoints/step-001000-epoch-24-loss=0.0100.safetensors");
  EXPECT_EQ(policy::Policy::load(d.string())->weight_files(),
            std::vector<std::string>{"checkpoints/step-001000-epoch-24-loss=0.0100.safetensors"});
  fs::copy_file(d / "checkpoints" / "step-000120-epoch-03-loss=0.0170.safetensors",
                d / "checkpoints" / "step-001000-epoch-25-loss=0.0090.safetensors");
  auto [code, what] = error_of([&] { fluxvla_weights_file(d); });
  EXPECT_EQ(code, ErrorCode::format);
  EXPECT_NE(what.find("more than one weight file for step 1000"), std::string::npos) << what;
  fs::remove_all(d);
}

TEST(FluxvlaLayout, ParameterNamesMapByPrefix) {
  EXPECT_EQ(fluxvla_to_lerobot_name("llm_backbone.layers.3.self_attn.q_proj.weight", "f"),
            "model.paligemma_with_expert.paligemma.model.language_model.layers.3.self_attn.q_proj.weight");
  EXPECT_EQ(fluxvla_to_lerobot_name("llm_backbone.embed_tokens.weight", "f"),
            "model.paligemma_with_expert.paligemma.model.language_model.embed_tokens.weight");
  EXPECT_EQ(fluxvla_to_lerobot_name("llm_expert.norm.dense.bias", "f"), "model.paligemma_with_expert.gemma_expert.model.norm.dense.bias");
  EXPECT_EQ(fluxvla_to_lerobot_name("vision_backbone.vision.vision_model.post_layernorm.weight", "f"),
            "model.paligemma_with_expert.paligemma.model.vision_tower.vision_model.post_layernorm.weight");
  EXPECT_EQ(fluxvla_to_lerobot_name("projector.projector.bias", "f"),
            "model.paligemma_with_expert.paligemma.model.multi_modal_projector.linear.bias");
  EXPECT_EQ(fluxvla_to_lerobot_name("time_mlp_out.projector.weight", "f"), "model.time_mlp_out.weight");
  EXPECT_EQ(fluxvla_to_lerobot_name("action_out_proj.projector.bias", "f"), "model.action_out_proj.bias");
  EXPECT_EQ(fluxvla_to_lerobot_name("llm_expert.embed_tokens.weight", "f"), std::nullopt);
  auto [code, what] = error_of([&] { fluxvla_to_lerobot_name("state_proj.projector.weight", "file.safetensors"); });
  EXPECT_EQ(code, ErrorCode::format);
  EXPECT_NE(what.find("file.safetensors: tensor 'state_proj.projector.weight' is not a PI05FlowMatching parameter"),
            std::string::npos)
      << what;
  // The opened store holds lerobot's names only, the dead expert embedding hidden.
  const TensorStore s = pi05_fluxvla_family().open_weights(kRoot / "libero_f32" / "checkpoint");
  for (const auto& n : s.names()) EXPECT_EQ(n.rfind("model.", 0), 0u) << n;
  EXPECT_FALSE(s.contains("llm_expert.embed_tokens.weight"));
}

TEST(FluxvlaNormalization, StatisticsFromDatasetStatisticsJson) {
  const fs::path dir = kRoot / "variant_bf16" / "checkpoint";
  const Json stats = read_json_file((dir / "dataset_statistics.json").string());
  ASSERT_TRUE(stats.contains("libero_90_no_noops"));  // the other entry, which must not be picked
  const Json& entry = stats.at("libero_10_no_noops");
  LoadedCheckpoint c = load_checkpoint(dir);
  EXPECT_FLOAT_EQ(c.normalization.input.eps, 1e-6f);  // FluxVLA's (x - mean) / (std + 1e-6)
  const auto& state = c.normalization.input.features.at("observation.state");
  const auto& action = c.normalization.output.features.at("action");
  EXPECT_EQ(state.mode, NormMode::mean_std);
  EXPECT_EQ(action.mode, NormMode::mean_std);
  const auto as_f = [](const Json& j) {
    std::vector<float> v;
    for (double x : j.get<std::vector<double>>()) v.push_back(float(x));
    return v;
  };
  EXPECT_EQ(state.stats.at("mean"), as_f(entry["proprio"]["mean"]));
  EXPECT_EQ(action.stats.at("std"), as_f(entry["action"]["std"]));
  EXPECT_EQ(c.model->spec().state_dim, 8);
  EXPECT_EQ(c.model->spec().action_dim, 7);
  EXPECT_EQ(c.model->spec().cameras,
            (std::vector<std::string>{"observation.images.wrist_image", "observation.images.image"}));

  // A mask (False: passes through) becomes mean 0, std 1; another statistics type is refused.
  const fs::path d = copy_case("libero_f32", "mask");
  Json s = read_json_file((d / "dataset_statistics.json").string());
  s["libero_10_no_noops"]["action"]["mask"] = {true, true, true, true, true, true, false};
  write_json(d / "dataset_statistics.json", s);
  const LoadedCheckpoint m = load_checkpoint(d);
  EXPECT_EQ(m.normalization.output.features.at("action").stats.at("mean").back(), 0.0f);
  EXPECT_EQ(m.normalization.output.features.at("action").stats.at("std").back(), 1.0f);
  Json cfg = read_json_file((d / "config.json").string());
  cfg["eval"]["denormalize_action"]["norm_type"] = "quantile";
  write_json(d / "config.json", cfg);
  auto [code, what] = error_of([&] { load_checkpoint(d); });
  EXPECT_EQ(code, ErrorCode::unsupported);
  EXPECT_NE(what.find("eval.denormalize_action.norm_type"), std::string::npos) << what;
  fs::remove_all(d);
}

TEST(FluxvlaConfig, WhatTetherDoesNotImplementIsRefusedByName) {
  const auto refused = [](const std::string& name, auto edit, const std::string& expect) {
    const fs::path d = copy_case("libero_f32", name);
    Json cfg = read_json_file((d / "config.json").string());
    edit(cfg);
    write_json(d / "config.json", cfg);
    auto [code, what] = error_of([&] { load_checkpoint(d); });
    EXPECT_NE(code, ErrorCode::internal) << name << ": loaded";
    EXPECT_NE(what.find(expect), std::string::npos) << name << ": " << what;
    fs::remove_all(d);
  };
  refused("conversation", [](Json& c) { c["eval"]["dataset"]["transforms"][2]["use_conversation"] = true; },
          "use_conversation");
  refused("rope", [](Json& c) { c["model"]["llm_backbone"]["rope_theta"] = 500000.0; }, "model.llm_backbone.rope_theta");
  refused("adarms", [](Json& c) { c["model"]["llm_expert"]["use_adarms"] = false; }, "model.llm_expert.use_adarms");
  refused("head", [](Json& c) { c["model"]["vision_backbone"]["vision_config"]["vision_use_head"] = true; },
          "vision_use_head");
  refused("sizes", [](Json& c) { c["eval"]["dataset"]["transforms"][1]["input_sizes"] = {{3, 224, 224}, {3, 224, 224}}; },
          "input_sizes");
  const fs::path d = copy_case("libero_f32", "no_tokenizer");
  fs::remove_all(d / "tokenizer");
  auto [code, what] = error_of([&] { load_checkpoint(d); });
  EXPECT_EQ(code, ErrorCode::not_found);
  EXPECT_NE(what.find("tokenizer.model: missing"), std::string::npos) << what;
  fs::remove(d / "dataset_statistics.json");
  std::tie(code, what) = error_of([&] { load_checkpoint(d); });
  EXPECT_EQ(code, ErrorCode::not_found);
  EXPECT_NE(what.find("dataset_statistics.json: missing"), std::string::npos) << what;
  fs::remove_all(d);
}

TEST(FluxvlaImages, AnotherSizeIsResizedWithAWarning) {
  auto p = policy::Policy::load((kRoot / "libero_f32" / "checkpoint").string());
  policy::Observation o;
  vision::Image img;
  img.height = 64;
  img.width = 80;
  img.rgb.assign(std::size_t(64 * 80 * 3), 90);
  o.images["observation.images.image"] = img;
  o.images["observation.images.wrist_image"] = vision::load_image((kRoot / "libero_f32" / "inputs" / "wrist_image_0.png").string());
  o.state.assign(std::size_t(p->spec().state_dim), 0.f);
  o.instruction = "pick up the red cube";
  const auto pred = p->predict({o});
  ASSERT_EQ(pred.items.size(), 1u);
  bool warned = false;
  for (const auto& w : pred.items[0].warnings) warned = warned || w.find("64x80 frame resized to 56x56") != std::string::npos;
  EXPECT_TRUE(warned);
  for (float v : pred.items[0].actions) EXPECT_TRUE(std::isfinite(v));
}
