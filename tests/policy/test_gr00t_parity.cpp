// GR00T N1.7 parity: every oracle case (tests/fixtures/gr00t_n17) is run through Tether end to end (the camera PNGs,
// the robot-unit state, the instruction, the oracle's noise) and compared with lerobot's GR00TN17 and its N1.7
// pre- and post-processing, intermediates included.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <map>

#include "core/safetensors.h"
#include "models/gr00t.h"
#include "policy/policy.h"

using namespace tether;
namespace fs = std::filesystem;

namespace {

// The stand-in Qwen3-VL backbone repository lives in a hub cache under the id the checkpoints name. Set for each load
// (the pi parity cases in the same binary use another hub cache), and read only while loading.
void use_gr00t_hub() { ::setenv("HF_HUB_CACHE", (fs::path(TETHER_FIXTURES_DIR) / "gr00t_hub").c_str(), 1); }

std::vector<std::string> cases() {
  std::vector<std::string> out;
  const fs::path root = fs::path(TETHER_FIXTURES_DIR) / "gr00t_n17";
  if (fs::exists(root))
    for (const auto& e : fs::directory_iterator(root))
      if (fs::exists(e.path() / "oracle.safetensors")) out.push_back(e.path().filename().string());
  std::sort(out.begin(), out.end());
  return out;
}

double max_abs(const std::vector<float>& a) {
  double m = 0;
  for (float v : a) m = std::max(m, double(std::fabs(v)));
  return m;
}

struct Captured {
  Shape shape;
  std::vector<float> values;
};

struct CaseRun {
  std::map<std::string, Captured> captured;
  cpu::Precision precision = cpu::Precision::fp32;  // what the model computed in
  std::vector<models::ModalityGroup> action_groups;
};

CaseRun run_case(const std::string& name, cpu::Precision precision) {
  const fs::path dir = fs::path(TETHER_FIXTURES_DIR) / "gr00t_n17" / name;
  const SafeTensorsFile oracle = SafeTensorsFile::open((dir / "oracle.safetensors").string());
  const auto& meta = oracle.metadata();
  models::LoadOptions options;
  options.precision = precision;
  options.embodiment = meta.at("embodiment_tag");
  use_gr00t_hub();
  auto policy = policy::Policy::load((dir / "checkpoint").string(), options);
  const auto& spec = policy->spec();
  policy::Observation o;
  o.state = oracle.get("input.state").to_f32();
  o.instruction = meta.at("instruction");
  o.noise = oracle.get("input.noise").to_f32();
  const Json files = Json::parse(meta.at("input_files"));
  for (auto it = files.begin(); it != files.end(); ++it) {
    o.images[it.key()] = vision::load_image((dir / it.value().get<std::string>()).string());
    const Tensor expected = oracle.get("input.image." + it.key());
    const auto& img = o.images[it.key()];
    EXPECT_EQ(std::memcmp(img.rgb.data(), expected.as<uint8_t>(), img.rgb.size()), 0) << it.key();
  }
  CaseRun run;
  run.action_groups = models::action_groups(spec);
  run.precision = spec.precision;
  policy->set_debug_hook([&](const std::string& n, const Tensor& t) { run.captured[n] = {t.shape, t.to_f32()}; });
  const policy::Prediction pred = policy->predict({o});
  run.captured["out.actions"] = {{1, spec.chunk_size, spec.action_dim}, pred.items.at(0).actions};
  run.captured["out.actions_chunk"] = run.captured.at("out.actions_normalized");
  return run;
}

// fp32 end to end: preprocessing exact but for float rounding; intermediates 1e-4 of their largest value (the vision
// tower and decoder compound float32 differences in summation order); the normalised chunk 1e-5 of its largest value.
double tolerance(const std::string& name, const std::vector<float>& ref) {
  if (name.rfind("pre.", 0) == 0 || name == "mid.position_ids") return 1e-6;
  if (name.rfind("out.", 0) == 0) return 1e-5 * std::max(1.0, max_abs(ref));
  return 1e-4 * std::max(1.0, max_abs(ref));
}

class Gr00tParity : public ::testing::TestWithParam<std::string> {};

TEST_P(Gr00tParity, MatchesUpstream) {
  const fs::path dir = fs::path(TETHER_FIXTURES_DIR) / "gr00t_n17" / GetParam();
  const SafeTensorsFile oracle = SafeTensorsFile::open((dir / "oracle.safetensors").string());
  CaseRun run = run_case(GetParam(), cpu::Precision::fp32);
  const bool libero = models::gr00t_applies_libero_transform(oracle.metadata().at("embodiment_tag"));
  std::printf("  %-24s %-28s %12s\n", ("[" + GetParam() + "]").c_str(), "tensor", "max |diff|");
  int compared = 0;
  for (const std::string& name : oracle.names()) {
    auto it = run.captured.find(name);
    if (it == run.captured.end()) continue;
    std::vector<float> want = oracle.get(name).to_f32(), got = it->second.values;
    // lerobot's LIBERO decode transform; Tether serves robot units and leaves it to the client (models/gr00t.h).
    if (name == "out.actions" && libero) models::libero_gripper_transform(got, run.action_groups);
    ASSERT_EQ(want.size(), got.size()) << name;
    double diff = 0;
    for (std::size_t i = 0; i < want.size(); ++i) diff = std::max(diff, std::fabs(double(want[i]) - double(got[i])));
    const double tol = tolerance(name, want);
    std::printf("  %-24s %-28s %12.3e%s\n", "", name.c_str(), diff, diff <= tol ? "" : "   <-- over tolerance");
    EXPECT_LE(diff, tol) << name;
    ++compared;
  }
  EXPECT_GE(compared, 20);
}

// bf16 and fp16 are reduced-precision modes: their error against upstream fp32 is measured and bounded, not hidden.
void expect_half_precision_bounded(const std::string& name, cpu::Precision precision) {
  const SafeTensorsFile oracle =
      SafeTensorsFile::open((fs::path(TETHER_FIXTURES_DIR) / "gr00t_n17" / name / "oracle.safetensors").string());
  const CaseRun run = run_case(name, precision);
  const std::vector<float> want = oracle.get("out.actions_chunk").to_f32(), got = run.captured.at("out.actions_chunk").values;
  ASSERT_EQ(want.size(), got.size());
  double diff = 0;
  for (std::size_t i = 0; i < want.size(); ++i) diff = std::max(diff, std::fabs(double(want[i]) - double(got[i])));
  std::printf("  [%s] %s out.actions_chunk max |diff| %.3e (max |value| %.3f)\n", name.c_str(),
              cpu::precision_name(precision), diff, max_abs(want));
  EXPECT_LT(diff, 0.05 * std::max(1.0, max_abs(want)));
  // The fixtures store bf16 weights, as the release does, so bf16 (and fp16, which holds every bf16 value of their
  // range) weights compute what fp32 computes: the error is fp32's. The mode itself must have been the one asked for.
  EXPECT_EQ(run.precision, precision);
}

TEST_P(Gr00tParity, Bf16ErrorIsBounded) { expect_half_precision_bounded(GetParam(), cpu::Precision::bf16); }
TEST_P(Gr00tParity, Fp16ErrorIsBounded) { expect_half_precision_bounded(GetParam(), cpu::Precision::fp16); }

INSTANTIATE_TEST_SUITE_P(Fixtures, Gr00tParity, ::testing::ValuesIn(cases()),
                         [](const auto& info) { return info.param; });

// N1.7's own real-time chunking (inpainting the leftover into the sampler's first rows, tools/oracle/gr00t_rtc_oracle.py)
// against lerobot driven as its RTC rollout engine drives it: the leftover in robot units, as a client holds it.
TEST(Gr00tRtc, MatchesLerobotsInpainting) {
  const fs::path source = fs::path(TETHER_FIXTURES_DIR) / "gr00t_n17" / "cam2_new";
  const SafeTensorsFile rtc = SafeTensorsFile::open(
      (fs::path(TETHER_FIXTURES_DIR) / "gr00t_n17_rtc" / "oracle.safetensors").string());
  const SafeTensorsFile oracle = SafeTensorsFile::open((source / "oracle.safetensors").string());
  models::LoadOptions options;
  options.embodiment = rtc.metadata().at("embodiment_tag");
  use_gr00t_hub();
  auto policy = policy::Policy::load((source / "checkpoint").string(), options);
  const auto& spec = policy->spec();
  policy::Observation o;
  o.state = oracle.get("input.state").to_f32();
  o.instruction = oracle.metadata().at("instruction");
  o.noise = rtc.get("input.noise").to_f32();
  const Json files = Json::parse(oracle.metadata().at("input_files"));
  for (auto it = files.begin(); it != files.end(); ++it)
    o.images[it.key()] = vision::load_image((source / it.value().get<std::string>()).string());
  std::vector<float> normalized;
  policy->set_debug_hook([&](const std::string& n, const Tensor& t) {
    if (n == "out.actions_normalized") normalized = t.to_f32();
  });
  auto diff = [](const std::vector<float>& a, const std::vector<float>& b) {
    EXPECT_EQ(a.size(), b.size());
    double m = 0;
    for (std::size_t i = 0; i < std::min(a.size(), b.size()); ++i) m = std::max(m, std::fabs(double(a[i]) - double(b[i])));
    return m;
  };
  policy->predict({o});
  const std::vector<float> plain = rtc.get("out.no_rtc.actions_normalized").to_f32();
  std::printf("  [gr00t rtc] %-8s normalised max |diff| %.3e\n", "no RTC", diff(normalized, plain));
  EXPECT_LE(diff(normalized, plain), 1e-5 * std::max(1.0, max_abs(plain)));

  const std::vector<float> prev = rtc.get("input.prev_actions").to_f32();
  // The leftover mapped back to model space is what upstream was fed.
  std::vector<float> back = prev;
  policy->output_normalizer().invert_unnormalize(spec.action_key, back.data(), int64_t(back.size()));
  EXPECT_LE(diff(back, rtc.get("input.prev_actions_normalized").to_f32()), 1e-6);
  int compared = 0;
  for (const auto& c : Json::parse(rtc.metadata().at("cases"))) {
    const std::string name = c.at("name");
    o.rtc = policy::Observation::Rtc{.prev_actions = prev,
                                     .inference_delay = c.at("inference_delay").get<int>(),
                                     .execution_horizon = c.at("execution_horizon").get<int>()};
    // The per-row velocity scale the sampler uses, against upstream's.
    models::DenoiseControl control;
    models::inpainting_rtc(back, spec.action_dim, spec.max_action_dim, spec.noise_rows(), o.rtc->execution_horizon,
                           o.rtc->inference_delay, spec.rtc_ramp_rate, control);
    EXPECT_LE(diff(control.velocity_scale, c.at("velocity_scale").get<std::vector<float>>()), 1e-7) << name;
    const policy::Prediction p = policy->predict({o});
    const std::vector<float> want = rtc.get("out." + name + ".actions").to_f32();
    const std::vector<float> want_norm = rtc.get("out." + name + ".actions_normalized").to_f32();
    const double dn = diff(normalized, want_norm), dr = diff(p.items.at(0).actions, want);
    std::printf("  [gr00t rtc] %-8s normalised max |diff| %.3e, robot units %.3e (max |action| %.2f)\n", name.c_str(),
                dn, dr, max_abs(want));
    EXPECT_LE(dn, 1e-5 * std::max(1.0, max_abs(want_norm))) << name;
    EXPECT_LE(dr, 1e-5 * std::max(1.0, max_abs(want))) << name;
    EXPECT_GT(diff(want_norm, plain), 1e-3) << name << ": the case must differ from plain sampling";
    ++compared;
  }
  EXPECT_GE(compared, 4);
}

}  // namespace

// Several embodiments of one checkpoint in one process: the shared part is loaded once (models::gr00t_shares_weights)
// and each embodiment, predicting in any order, answers bit for bit what a model loaded for it alone answers.
std::vector<float> embodiment_chunk(policy::Policy& p, uint64_t seed) {
  policy::Observation o = policy::synthetic_observation(p.spec());
  for (std::size_t i = 0; i < o.state.size(); ++i) o.state[i] = 0.1f * float(i % 5) - 0.2f;
  o.instruction = "pick up the cube";
  o.seed = seed;
  return p.predict({o}).items.at(0).actions;
}

void expect_embodiments_share_one_load(const fs::path& checkpoint, const std::string& a, const std::string& b) {
  auto load = [&](const std::string& tag, std::shared_ptr<backend::Backend> be) {
    models::LoadOptions options;
    options.embodiment = tag;
    options.backend = std::move(be);
    return policy::Policy::load(checkpoint.string(), options);
  };
  const auto shared_be = backend::make_backend("cpu");
  auto pa = load(a, shared_be), pb = load(b, shared_be);
  EXPECT_TRUE(models::gr00t_shares_weights(pa->model(), pb->model()));
  EXPECT_EQ(pa->spec().embodiment, a);
  EXPECT_EQ(pb->spec().embodiment, b);
  const std::vector<float> a1 = embodiment_chunk(*pa, 7), b1 = embodiment_chunk(*pb, 7), a2 = embodiment_chunk(*pa, 7);
  EXPECT_EQ(a1, a2);
  // Alone: another backend is another shared part.
  auto alone_a = load(a, backend::make_backend("cpu"));
  auto alone_b = load(b, backend::make_backend("cpu"));
  EXPECT_FALSE(models::gr00t_shares_weights(alone_a->model(), alone_b->model()));
  EXPECT_FALSE(models::gr00t_shares_weights(pa->model(), alone_a->model()));
  EXPECT_EQ(a1, embodiment_chunk(*alone_a, 7));
  EXPECT_EQ(b1, embodiment_chunk(*alone_b, 7));
  EXPECT_NE(a1, b1);
  // Loading a tag again reuses its slot; an unknown one is refused and leaves the shared model serving.
  auto pa_again = load(a, shared_be);
  EXPECT_TRUE(models::gr00t_shares_weights(pa->model(), pa_again->model()));
  EXPECT_EQ(embodiment_chunk(*pa_again, 7), a1);
  EXPECT_THROW(load("no_such_robot", shared_be), Error);
  EXPECT_EQ(embodiment_chunk(*pb, 7), b1);
}

TEST(Gr00tEmbodiments, TwoTagsShareOneLoadAndMatchSeparateLoads) {
  use_gr00t_hub();
  expect_embodiments_share_one_load(fs::path(TETHER_FIXTURES_DIR) / "gr00t_n17" / "cam1_libero" / "checkpoint",
                                    "libero_sim", "new_embodiment");
}

// Relative actions (tools/oracle/gr00t_relative_oracle.py): a checkpoint with use_relative_action, an EEF group in
// XYZ_ROT6D with per-step statistics and a NON_EEF group, decoded by lerobot's GrootN17ActionDecodeStep against the
// request's raw state. The model output, the relative values before re-anchoring and the absolute actions are compared.
TEST(Gr00tRelative, MatchesLerobotsDecode) {
  const fs::path dir = fs::path(TETHER_FIXTURES_DIR) / "gr00t_n17_relative";
  const SafeTensorsFile oracle = SafeTensorsFile::open((dir / "oracle.safetensors").string());
  use_gr00t_hub();
  auto policy = policy::Policy::load((dir / "checkpoint").string());
  const auto& spec = policy->spec();
  EXPECT_TRUE(spec.relative_actions);
  EXPECT_TRUE(spec.rtc_refused_for_relative());  // lerobot turns RTC off for GR00T's relative groups
  policy::Observation o;
  o.state = oracle.get("input.state").to_f32();
  o.instruction = oracle.metadata().at("instruction");
  o.noise = oracle.get("input.noise").to_f32();
  const Json files = Json::parse(oracle.metadata().at("input_files"));
  for (auto it = files.begin(); it != files.end(); ++it)
    o.images[it.key()] = vision::load_image((dir / it.value().get<std::string>()).string());
  std::vector<float> normalized;
  policy->set_debug_hook([&](const std::string& n, const Tensor& t) {
    if (n == "out.actions_normalized") normalized = t.to_f32();
  });
  {
    policy::Observation with_rtc = o;
    with_rtc.rtc = policy::Observation::Rtc{};
    with_rtc.rtc->prev_actions.assign(std::size_t(spec.action_dim), 0.f);
    try {
      policy->predict({with_rtc});
      ADD_FAILURE() << "an RTC leftover was accepted for GR00T's relative groups";
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find("relative to the state"), std::string::npos) << e.what();
    }
  }
  const std::vector<float> got = policy->predict({o}).items.at(0).actions;
  auto diff = [](const std::vector<float>& a, const std::vector<float>& b) {
    EXPECT_EQ(a.size(), b.size());
    double m = 0;
    for (std::size_t i = 0; i < std::min(a.size(), b.size()); ++i) m = std::max(m, std::fabs(double(a[i]) - double(b[i])));
    return m;
  };
  // The model's normalised rows: upstream's chunk cut to the valid steps and the action groups' columns.
  const Tensor chunk = oracle.get("out.actions_chunk");
  const std::vector<float> chunk_values = chunk.to_f32();
  const int64_t rows = spec.chunk_size, dim = spec.action_dim, width = chunk.shape.back();
  std::vector<float> want_norm;
  for (int64_t r = 0; r < rows; ++r)
    for (int64_t c = 0; c < dim; ++c) want_norm.push_back(chunk_values[std::size_t(r * width + c)]);
  const std::vector<float> want = oracle.get("out.actions").to_f32();
  const double dn = diff(normalized, want_norm), da = diff(got, want);
  std::printf("  [gr00t relative] normalised max |diff| %.3e; absolute actions %.3e (max |action| %.2f)\n", dn, da,
              max_abs(want));
  EXPECT_LE(dn, 1e-5 * std::max(1.0, max_abs(want_norm)));
  EXPECT_LE(da, 1e-5 * std::max(1.0, max_abs(want)));
  // Before re-anchoring: the relative values alone (the EEF group's first 9 columns, the joints' next 4).
  std::vector<float> relative = normalized;
  policy->output_normalizer().unnormalize(spec.action_key, relative.data(), int64_t(relative.size()));
  std::vector<float> eef, joints;
  for (int64_t r = 0; r < rows; ++r) {
    eef.insert(eef.end(), relative.begin() + r * dim, relative.begin() + r * dim + 9);
    joints.insert(joints.end(), relative.begin() + r * dim + 9, relative.begin() + r * dim + 13);
  }
  EXPECT_LE(diff(eef, oracle.get("out.relative.eef").to_f32()), 1e-5);
  EXPECT_LE(diff(joints, oracle.get("out.relative.joints").to_f32()), 1e-5);
  // Real-time chunking is off for relative actions, as lerobot turns it off.
  o.rtc = policy::Observation::Rtc{.prev_actions = std::vector<float>(got.begin(), got.begin() + dim)};
  EXPECT_THROW(policy->predict({o}), Error);
}
