// GR00T N1.6 against the oracle (tools/oracle/gr00t_n16_oracle.py, tests/fixtures/gr00t_n16): N1.6's own code
// (Isaac-GR00T) is not on PyPI, so the fixtures run transformers' Siglip2VisionModel and Qwen3Model, lerobot's DiT
// head, and restate the Eagle glue and processor from the Isaac-GR00T source. Checked here:
//   blocks   the SigLIP2 position-table resize and tower (four patch grids), Qwen3 cut at select_layer with its final
//            norm (each prompt of the left-padded batch on its own);
//   cases    end to end from camera frames, instruction and raw state to actions (three cases, two embodiments),
//            every recorded intermediate (pixels, tokens, vision rows, projector rows, features, state token, DiT,
//            velocity, actions).
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>

#include "backend/backend.h"
#include "core/safetensors.h"
#include "models/blocks/decoder.h"
#include "models/blocks/vision_tower.h"
#include "models/gr00t.h"
#include "models/weights.h"
#include "policy/policy.h"
#include "text/tokenizer.h"
#include "vision/gr00t_preprocess.h"
#include "vision/image.h"
#include "eagle_hub.h"

using namespace tether;
namespace fs = std::filesystem;

namespace {

const fs::path kRoot = fs::path(TETHER_FIXTURES_DIR) / "gr00t_n16";

void use_eagle_hub(bool as_released = false) {
  ::setenv("HF_HUB_CACHE", tether::testing::eagle_hub_cache(as_released).c_str(), 1);
}

double max_abs(const std::vector<float>& a) {
  double m = 0;
  for (float v : a) m = std::max(m, double(std::fabs(v)));
  return m;
}

double max_diff(const std::vector<float>& a, const std::vector<float>& b) {
  EXPECT_EQ(a.size(), b.size());
  double m = 0;
  for (std::size_t i = 0; i < std::min(a.size(), b.size()); ++i)
    m = std::max(m, std::fabs(double(a[i]) - double(b[i])));
  return m;
}

Json eagle_config() { return read_json_file((kRoot / "eagle" / "config.json").string()); }

}  // namespace

TEST(Gr00tN16Blocks, Siglip2PositionTableAndTower) {
  const SafeTensorsFile oracle = SafeTensorsFile::open((kRoot / "blocks" / "vision" / "oracle.safetensors").string());
  auto be = backend::make_backend("cpu");
  models::Weights w(models::TensorStore::open_dir((kRoot / "checkpoint").string()));
  const models::VisionConfig cfg =
      models::VisionConfig::from_siglip2_json(eagle_config().at("vision_config"), "eagle/config.json");
  models::VisionTower tower;
  const std::string prefix = "backbone.model.vision_model.vision_model.";
  tower.load(*be, w, prefix, cfg, cpu::Precision::fp32);
  const float* table = w.f32(prefix + "embeddings.position_embedding.weight", {cfg.table_side * cfg.table_side, cfg.hidden});
  int images = 0;
  for (const char* name : {"square6", "wide4x6", "tall8x4", "table4x4"}) {
    const std::string p = std::string(name);
    const Tensor img = oracle.get(p + ".image");
    const int64_t H = img.dim(0), W = img.dim(1), gh = H / cfg.patch, gw = W / cfg.patch, n = gh * gw;
    const std::vector<float> pos = models::resize_table_bilinear_aa(table, cfg.table_side, cfg.hidden, gh, gw);
    const std::vector<float> want_pos = oracle.get(p + ".pos_embed").to_f32();
    const double dpos = max_diff(pos, want_pos);
    // Pixels [3, H, W] as the Eagle processor gives them.
    std::vector<float> pixels(std::size_t(3 * H * W));
    const uint8_t* rgb = img.as<uint8_t>();
    for (int64_t i = 0; i < H * W; ++i)
      for (int c = 0; c < 3; ++c) pixels[std::size_t(c * H * W + i)] = (float(rgb[i * 3 + c]) - 127.5f) / 127.5f;
    auto px = be->alloc<float>(3 * H * W);
    be->upload(pixels.data(), 3 * H * W, px.at());
    auto out = be->alloc<float>(n * cfg.hidden);
    tower.forward(*be, px.at(), 1, H, W, out.at());
    std::vector<float> got(std::size_t(n * cfg.hidden));
    be->download(backend::Ptr<const float>(out.at()), n * cfg.hidden, got.data());
    const std::vector<float> want = oracle.get(p + ".last_hidden_state").to_f32();
    const double dout = max_diff(got, want);
    std::printf("  [vision %-8s] %lldx%lld patches: position table max |diff| %.3e, tower %.3e (max |value| %.2f)\n",
                name, (long long)gh, (long long)gw, dpos, dout, max_abs(want));
    EXPECT_LE(dpos, 1e-6 * std::max(1.0, max_abs(want_pos))) << name;
    EXPECT_LE(dout, 1e-5 * std::max(1.0, max_abs(want))) << name;
    ++images;
  }
  EXPECT_EQ(images, 4);
}

TEST(Gr00tN16Blocks, Qwen3CutAtSelectLayerWithItsFinalNorm) {
  const SafeTensorsFile oracle = SafeTensorsFile::open((kRoot / "blocks" / "llm" / "oracle.safetensors").string());
  auto be = backend::make_backend("cpu");
  models::Weights w(models::TensorStore::open_dir((kRoot / "checkpoint").string()));
  const Json ckpt = read_json_file((kRoot / "checkpoint" / "config.json").string());
  const Json text = eagle_config().at("text_config");
  models::DecoderConfig cfg = models::DecoderConfig::from_llama_json(text, "eagle/config.json");
  cfg.qk_norm = true;
  cfg.rope_wavelength = text.at("rope_theta").get<float>();
  const std::string prefix = "backbone.model.language_model.model.";
  models::DecoderStack stack;
  stack.load(*be, w, prefix + "layers.", cfg, ckpt.at("select_layer").get<int64_t>(), cpu::Precision::fp32, false);
  const int64_t D = cfg.hidden;
  auto norm = be->constant(w.f32(prefix + "norm.weight", {D}), D);
  const Tensor embeds = oracle.get("inputs_embeds");
  const std::vector<float> all = embeds.to_f32();
  const std::vector<float> mask = oracle.get("attention_mask").to_f32();
  const int64_t Lpad = embeds.dim(1);
  for (int64_t row = 0; row < 2; ++row) {
    // The prompt's own tokens (the batch is left-padded), alone: batch 1, positions 0..L-1.
    int64_t first = 0;
    while (first < Lpad && mask[std::size_t(row * Lpad + first)] == 0) ++first;
    const int64_t L = Lpad - first;
    auto x = be->alloc<float>(L * D), y = be->alloc<float>(L * D);
    be->upload(all.data() + (row * Lpad + first) * D, L * D, x.at());
    std::vector<int64_t> pos(static_cast<std::size_t>(L));
    for (int64_t i = 0; i < L; ++i) pos[std::size_t(i)] = i;
    auto positions = be->alloc<int64_t>(L);
    be->upload(pos.data(), L, positions.at());
    std::vector<uint8_t> causal(std::size_t(L * L), 0);
    for (int64_t i = 0; i < L; ++i)
      for (int64_t j = 0; j <= i; ++j) causal[std::size_t(i * L + j)] = 1;
    auto m = be->alloc<uint8_t>(L * L);
    be->upload(causal.data(), L * L, m.at());
    models::KvCache cache;
    cache.resize(*be, stack.layers(), 1, L, cfg.kv_heads * cfg.head_dim);
    stack.forward(*be, x.at(), 1, L, positions.at(), m.at(), cache);
    be->rms_norm(x.at(), L, D, norm.at(), cfg.rms_norm_eps, y.at());
    std::vector<float> got(std::size_t(L * D));
    be->download(backend::Ptr<const float>(y.at()), L * D, got.data());
    const std::vector<float> want = oracle.get("single" + std::to_string(row) + ".last_hidden_state").to_f32();
    const double d = max_diff(got, want);
    std::printf("  [llm prompt %lld] %lld tokens: last_hidden_state max |diff| %.3e (max |value| %.2f)\n",
                (long long)row, (long long)L, d, max_abs(want));
    EXPECT_LE(d, 1e-5 * std::max(1.0, max_abs(want)));
  }
}

class Gr00tN16Parity : public ::testing::TestWithParam<std::string> {};

namespace {

// One case through Tether at `precision`, every debug tensor captured, plus the robot-unit actions.
std::map<std::string, std::vector<float>> run_case(const std::string& name, cpu::Precision precision,
                                                   bool eagle_as_released = false, const fs::path& root = kRoot) {
  const fs::path dir = root / "cases" / name;
  const SafeTensorsFile oracle = SafeTensorsFile::open((dir / "oracle.safetensors").string());
  const auto& meta = oracle.metadata();
  models::LoadOptions options;
  options.precision = precision;
  options.embodiment = meta.at("embodiment_tag");
  use_eagle_hub(eagle_as_released);
  auto policy = policy::Policy::load((root / "checkpoint").string(), options);
  EXPECT_EQ(policy->spec().family, "gr00t_n16");
  EXPECT_EQ(policy->spec().precision, precision);
  policy::Observation o;
  for (const auto& g : Json::parse(meta.at("state_groups"))) {
    const std::vector<float> v = oracle.get("input.state." + g.at(0).get<std::string>()).to_f32();
    o.state.insert(o.state.end(), v.begin(), v.end());
  }
  o.instruction = meta.at("instruction");
  o.noise = oracle.get("input.noise").to_f32();
  const Json files = Json::parse(meta.at("input_files"));
  for (auto it = files.begin(); it != files.end(); ++it)
    o.images[it.key()] = vision::load_image((dir / it.value().get<std::string>()).string());
  std::map<std::string, std::vector<float>> captured;
  policy->set_debug_hook([&](const std::string& n, const Tensor& t) { captured[n] = t.to_f32(); });
  const policy::Prediction pred = policy->predict({o});
  captured["out.actions"] = pred.items.at(0).actions;
  return captured;
}

// Every tensor the oracle recorded for case `name` under `root` that Tether also produces, within tolerance.
void expect_matches_oracle(const fs::path& root, const std::string& name) {
  const fs::path dir = root / "cases" / name;
  const SafeTensorsFile oracle = SafeTensorsFile::open((dir / "oracle.safetensors").string());
  const std::map<std::string, std::vector<float>> captured =
      run_case(name, cpu::Precision::fp32, /*eagle_as_released=*/false, root);
  std::printf("  %-24s %-28s %12s\n", ("[" + name + "]").c_str(), "tensor", "max |diff|");
  int compared = 0;
  for (const std::string& tensor : oracle.names()) {
    auto it = captured.find(tensor);
    if (it == captured.end()) continue;
    const std::vector<float> want = oracle.get(tensor).to_f32();
    ASSERT_EQ(want.size(), it->second.size()) << tensor;
    const double d = max_diff(it->second, want);
    // Tokens and the state encoding exact but for float rounding; intermediates 1e-4 of their largest value; the
    // sampler's output and the actions 1e-5.
    const double tol = tensor.rfind("pre.", 0) == 0 ? 1e-6
                       : tensor.rfind("out.", 0) == 0 ? 1e-5 * std::max(1.0, max_abs(want))
                                                    : 1e-4 * std::max(1.0, max_abs(want));
    std::printf("  %-24s %-28s %12.3e%s\n", "", tensor.c_str(), d, d <= tol ? "" : "   <-- over tolerance");
    EXPECT_LE(d, tol) << tensor;
    ++compared;
  }
  EXPECT_GE(compared, 12);
}

}  // namespace

TEST_P(Gr00tN16Parity, MatchesTheOracleEndToEnd) { expect_matches_oracle(kRoot, GetParam()); }

// The decodes of Isaac-GR00T's StateActionProcessor.unapply_action that the cases above do not reach
// (tests/fixtures/gr00t_n16_decode, tools/oracle/gr00t_n16_decode_oracle.py), each an embodiment of one checkpoint.
const fs::path kDecodeRoot = fs::path(TETHER_FIXTURES_DIR) / "gr00t_n16_decode";

// use_relative_action: an EEF group in XYZ_ROT6D with per-step statistics and a NON_EEF group, made absolute against
// the request's state, beside an absolute gripper. Every recorded tensor, then the re-anchoring's effect.
TEST(Gr00tN16Decode, RelativeActionsMatchIsaacGr00t) {
  expect_matches_oracle(kDecodeRoot, "relative_arm");
  const SafeTensorsFile oracle =
      SafeTensorsFile::open((kDecodeRoot / "cases" / "relative_arm" / "oracle.safetensors").string());
  const std::vector<float> want = oracle.get("out.actions").to_f32(), rel = oracle.get("out.relative.eef").to_f32();
  EXPECT_EQ(want.size(), std::size_t(6 * 14));
  // The re-anchoring moved the eef rows: the absolute chunk is not the relative one.
  double moved = 0;
  for (std::size_t r = 0; r < 6; ++r) moved = std::max(moved, double(std::fabs(want[r * 14] - rel[r * 9])));
  EXPECT_GT(moved, 0.1);
}

// mean_std_embedding_keys in the action modality (Isaac-GR00T's oxe_widowx / oxe_google configs): those groups
// decode as x * std + mean, unclipped, and a dimension whose std is 0 passes the model's value through.
TEST(Gr00tN16Decode, MeanStdActionsMatchIsaacGr00t) {
  expect_matches_oracle(kDecodeRoot, "mean_std_arm");
  const auto captured = run_case("mean_std_arm", cpu::Precision::fp32, false, kDecodeRoot);
  const std::vector<float>& actions = captured.at("out.actions");
  const std::vector<float>& pred = captured.at("out.action_pred");  // [8][16] normalised
  ASSERT_EQ(actions.size(), std::size_t(6 * 7));
  for (std::size_t r = 0; r < 6; ++r) EXPECT_EQ(actions[r * 7 + 4], pred[r * 16 + 4]) << "row " << r;  // rpy[1]
}

// bf16 and fp16: measured against upstream fp32 and bounded. The fixture's weights are bf16, as the release's are, so
// both compute the fp32 numbers here; the mode itself must be the one asked for (run_case checks).
TEST_P(Gr00tN16Parity, HalfPrecisionErrorIsBounded) {
  const SafeTensorsFile oracle =
      SafeTensorsFile::open((kRoot / "cases" / GetParam() / "oracle.safetensors").string());
  const std::vector<float> want = oracle.get("out.action_pred").to_f32();
  for (const cpu::Precision p : {cpu::Precision::bf16, cpu::Precision::fp16}) {
    const auto captured = run_case(GetParam(), p);
    const double d = max_diff(captured.at("out.action_pred"), want);
    std::printf("  [%s] %s out.action_pred max |diff| %.3e (max |value| %.3f)\n", GetParam().c_str(),
                cpu::precision_name(p), d, max_abs(want));
    EXPECT_LT(d, 0.05 * std::max(1.0, max_abs(want)));
  }
}

// Isaac-GR00T ships the Eagle tokenizer as vocab.json + merges.txt, with no tokenizer.json: read that way, every case
// tokenizes to the oracle's ids and gives its actions.
TEST_P(Gr00tN16Parity, EagleTokenizerAsReleasedGivesTheSameTokens) {
  const SafeTensorsFile oracle =
      SafeTensorsFile::open((kRoot / "cases" / GetParam() / "oracle.safetensors").string());
  const auto captured = run_case(GetParam(), cpu::Precision::fp32, /*eagle_as_released=*/true);
  EXPECT_EQ(captured.at("pre.input_ids"), oracle.get("pre.input_ids").to_f32());
  const std::vector<float> want = oracle.get("out.action_pred").to_f32();
  EXPECT_LE(max_diff(captured.at("out.action_pred"), want), 1e-5 * std::max(1.0, max_abs(want)));
}

INSTANTIATE_TEST_SUITE_P(Cases, Gr00tN16Parity,
                         ::testing::Values("cam1_libero_panda", "cam2_new_embodiment", "long_instruction"),
                         [](const auto& info) { return info.param; });

// Several embodiments of one N1.6 checkpoint share one load, each with its own state encoding and category rows
// (the N1.7 test's counterpart, tests/policy/test_gr00t_parity.cpp).
TEST(Gr00tN16Embodiments, TwoTagsShareOneLoadAndMatchSeparateLoads) {
  use_eagle_hub();
  const fs::path checkpoint = kRoot / "checkpoint";
  auto load = [&](const std::string& tag, std::shared_ptr<backend::Backend> be) {
    models::LoadOptions options;
    options.embodiment = tag;
    options.backend = std::move(be);
    return policy::Policy::load(checkpoint.string(), options);
  };
  auto chunk = [](policy::Policy& p) {
    policy::Observation o = policy::synthetic_observation(p.spec());
    for (std::size_t i = 0; i < o.state.size(); ++i) o.state[i] = 0.1f * float(i % 5) - 0.2f;
    o.instruction = "pick up the cube";
    o.seed = 3;
    return p.predict({o}).items.at(0).actions;
  };
  const auto be = backend::make_backend("cpu");
  auto pa = load("libero_panda", be), pb = load("new_embodiment", be);
  EXPECT_TRUE(models::gr00t_shares_weights(pa->model(), pb->model()));
  const std::vector<float> a = chunk(*pa), b = chunk(*pb);
  EXPECT_EQ(chunk(*pa), a);
  EXPECT_EQ(chunk(*load("libero_panda", backend::make_backend("cpu"))), a);
  EXPECT_EQ(chunk(*load("new_embodiment", backend::make_backend("cpu"))), b);
}

// Opt-in (scripts/check_isaac_gr00t.sh): a real Eagle directory, as Isaac-GR00T vendors it, against what its own
// Eagle3_VLProcessor produced (tools/oracle/eagle_release_check.py, run under Isaac-GR00T's transformers pin). Checked:
// the pixel values of frames of several sizes (smart_resize, Pillow bicubic, normalisation), the prompt's ids through
// the chat template and the image-placeholder expansion, and the tokenizer on the shared 1,773-string corpus.
TEST(Gr00tN16EagleRelease, ProcessorAndTokenizerMatchTheRealDirectory) {
  const char* eagle = std::getenv("TETHER_EAGLE_DIR");
  const char* expected = std::getenv("TETHER_EAGLE_EXPECTED");
  if (!eagle || !expected)
    GTEST_SKIP() << "TETHER_EAGLE_DIR and TETHER_EAGLE_EXPECTED unset (scripts/check_isaac_gr00t.sh)";
  const fs::path out = expected;
  const Json meta = read_json_file((out / "meta.json").string());
  const SafeTensorsFile want = SafeTensorsFile::open((out / "expected.safetensors").string());
  const text::PretrainedTokenizer tok = text::load_pretrained_tokenizer(eagle);
  std::printf("  tokenizer read from %s (%d tokens)\n", tok.source.c_str(), tok.tokenizer.vocab_size());
  EXPECT_EQ(tok.tokenizer.token_to_id("<IMG_CONTEXT>"), meta.at("image_token_index").get<int32_t>());

  const Json& cases = meta.at("cases");
  for (std::size_t k = 0; k < cases.size(); ++k) {
    const Json& c = cases[k];
    const std::string key = "case" + std::to_string(k);
    std::vector<int64_t> image_tokens;
    double pixel_diff = 0;
    for (std::size_t j = 0; j < c.at("frames").size(); ++j) {
      const vision::EagleFrame f =
          vision::eagle_process_image(vision::load_image((out / c.at("frames")[j].get<std::string>()).string()));
      const auto size = c.at("image_sizes")[j].get<std::vector<int>>();
      EXPECT_EQ(f.image.height, size.at(0)) << key << " frame " << j;
      EXPECT_EQ(f.image.width, size.at(1)) << key << " frame " << j;
      const std::vector<float> pixels = want.get(key + ".pixels" + std::to_string(j)).to_f32();
      if (pixels.size() == f.pixels.size())
        pixel_diff = std::max(pixel_diff, max_diff(f.pixels, pixels));
      else
        ADD_FAILURE() << key << " frame " << j << ": " << f.pixels.size() << " pixel values, upstream "
                      << pixels.size();
      image_tokens.push_back(models::gr00t_n16_image_tokens(f.image.height, f.image.width));
    }
    const std::vector<int32_t> ids =
        tok.tokenizer.encode(models::gr00t_n16_prompt(c.at("language").get<std::string>(), image_tokens), false);
    const std::vector<float> want_ids = want.get(key + ".input_ids").to_f32();
    const std::vector<float> got_ids(ids.begin(), ids.end());
    EXPECT_EQ(got_ids, want_ids) << key << ": the prompt's ids differ from the Eagle processor's";
    std::printf("  [%s] %zu frames, %zu tokens: ids %s, pixel values max |diff| %.1e\n", key.c_str(),
                c.at("frames").size(), ids.size(), got_ids == want_ids ? "identical" : "DIFFER", pixel_diff);
    EXPECT_EQ(pixel_diff, 0.0) << key;
  }

  std::ifstream corpus(out / "tokenizer_cases.jsonl");
  int checked = 0, failed = 0;
  for (std::string line; std::getline(corpus, line);) {
    const Json row = Json::parse(line);
    const std::vector<int32_t> got = tok.tokenizer.encode(row.at("text").get<std::string>(), false);
    ++checked;
    if (got != row.at("ids").get<std::vector<int32_t>>() && failed++ < 5)
      ADD_FAILURE() << "corpus string '" << row.at("text").get<std::string>() << "' tokenizes differently";
  }
  std::printf("  tokenizer corpus: %d strings, %d differ\n", checked, failed);
  EXPECT_GT(checked, 1000);
  EXPECT_EQ(failed, 0);
}
