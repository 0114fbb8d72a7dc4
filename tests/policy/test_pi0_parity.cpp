// pi0 and pi0.5 parity: every oracle fixture case of both families is run through Tether end to end (image files,
// robot-unit state, instruction, the oracle's noise) and compared with upstream lerobot, intermediates included; the
// FluxVLA cases against FluxVLA's processing restated around lerobot's network (tests/fixtures/pi05_fluxvla).
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <map>

#include "core/safetensors.h"
#include "policy/policy.h"

using namespace tether;
namespace fs = std::filesystem;

namespace {

// The stand-in PaliGemma tokenizer lives in a hub cache under its real repo id, as upstream loaded it. Set for each load
// (the GR00T cases in the same binary use another hub cache).
void use_paligemma_hub() { ::setenv("HF_HUB_CACHE", (fs::path(TETHER_FIXTURES_DIR) / "paligemma_hub").c_str(), 1); }

struct Captured {
  Shape shape;
  std::vector<float> values;
};

std::vector<std::string> cases() {
  std::vector<std::string> out;
  for (const char* family : {"pi0", "pi05", "pi05_fluxvla"}) {
    const fs::path root = fs::path(TETHER_FIXTURES_DIR) / family;
    if (!fs::exists(root)) continue;
    for (const auto& e : fs::directory_iterator(root))
      if (fs::exists(e.path() / "oracle.safetensors")) out.push_back(std::string(family) + "/" + e.path().filename().string());
  }
  std::sort(out.begin(), out.end());
  return out;
}

double max_abs_diff(const std::vector<float>& a, const std::vector<float>& b) {
  double m = 0;
  for (std::size_t i = 0; i < a.size(); ++i) m = std::max(m, std::fabs(double(a[i]) - double(b[i])));
  return m;
}

double max_abs(const std::vector<float>& a) {
  double m = 0;
  for (float v : a) m = std::max(m, double(std::fabs(v)));
  return m;
}

// Tolerances, fp32 end to end: preprocessing exact up to 1e-6; the normalised chunk within 1e-5 relative to its
// largest value; robot-unit actions scale with the stats; intermediates deep in the network 1e-4 relative.
double tolerance(const std::string& name, const std::vector<float>& ref) {
  if (name.rfind("pre.", 0) == 0) return 1e-6;
  if (name.rfind("out.", 0) == 0) return 1e-5 * std::max(1.0, max_abs(ref));
  return 1e-4 * std::max(1.0, max_abs(ref));
}

// Rows [B, L, ...] of `values` where `pad` ([B, L]) is 1, item after item: what a prefix holds for real tokens,
// whatever slots the layout gave masked ones.
std::vector<float> real_rows(const std::vector<float>& values, const std::vector<float>& pad, int64_t B, int64_t L,
                             std::vector<int64_t>* per_item = nullptr) {
  const int64_t row = int64_t(values.size()) / (B * L);
  std::vector<float> out;
  for (int64_t b = 0; b < B; ++b) {
    int64_t n = 0;
    for (int64_t t = 0; t < L; ++t) {
      if (pad[b * L + t] == 0.f) continue;
      out.insert(out.end(), values.begin() + (b * L + t) * row, values.begin() + (b * L + t + 1) * row);
      ++n;
    }
    if (per_item) per_item->push_back(n);
  }
  return out;
}

std::map<std::string, Captured> run_case(const std::string& name, cpu::Precision precision) {
  const fs::path dir = fs::path(TETHER_FIXTURES_DIR) / name;
  const SafeTensorsFile oracle = SafeTensorsFile::open((dir / "oracle.safetensors").string());
  const Json cameras = Json::parse(oracle.metadata().at("cameras"));
  const Json instructions = Json::parse(oracle.metadata().at("instructions"));
  const Json files = Json::parse(oracle.metadata().at("input_files"));
  models::LoadOptions options;
  options.precision = precision;
  use_paligemma_hub();
  auto policy = policy::Policy::load((dir / "checkpoint").string(), options);
  const auto& spec = policy->spec();
  const Tensor state = oracle.get("input.state");
  const Tensor noise = oracle.get("input.noise");
  const int64_t B = state.dim(0);
  const std::vector<float> states = state.to_f32(), noises = noise.to_f32();

  std::vector<policy::Observation> batch(B);
  for (int64_t b = 0; b < B; ++b) {
    policy::Observation& o = batch[b];
    o.state.assign(states.begin() + b * state.dim(1), states.begin() + (b + 1) * state.dim(1));
    o.instruction = instructions.at(b).get<std::string>();
    o.noise.assign(noises.begin() + b * spec.chunk_size * spec.max_action_dim,
                   noises.begin() + (b + 1) * spec.chunk_size * spec.max_action_dim);
    for (const auto& cam : cameras) {
      const std::string key = cam.get<std::string>();
      if (!files.contains(key)) continue;  // a camera the case leaves out
      o.images[key] = vision::load_image((dir / "inputs" / files.at(key).at(b).get<std::string>()).string());
      const Tensor expected = oracle.get("input.image." + key);
      const auto& img = o.images[key];
      EXPECT_EQ(std::memcmp(img.rgb.data(), expected.as<uint8_t>() + b * img.rgb.size(), img.rgb.size()), 0)
          << key << " item " << b << " decodes differently from PIL";
    }
  }
  std::map<std::string, Captured> captured;
  policy->set_debug_hook([&](const std::string& n, const Tensor& t) { captured[n] = {t.shape, t.to_f32()}; });
  const policy::Prediction pred = policy->predict(batch);
  Captured actions{{B, spec.chunk_size, spec.action_dim}, {}};
  for (const auto& item : pred.items) actions.values.insert(actions.values.end(), item.actions.begin(), item.actions.end());
  captured["out.actions"] = actions;
  return captured;
}

class PiParity : public ::testing::TestWithParam<std::string> {};

TEST_P(PiParity, MatchesUpstream) {
  const fs::path dir = fs::path(TETHER_FIXTURES_DIR) / GetParam();
  const SafeTensorsFile oracle = SafeTensorsFile::open((dir / "oracle.safetensors").string());
  const auto captured = run_case(GetParam(), cpu::Precision::fp32);
  std::printf("  %-44s %-20s %12s\n", ("[" + GetParam() + "]").c_str(), "shape", "max |diff|");
  // Prefix intermediates: upstream keeps masked slots (absent cameras, padding) that Tether leaves out, so only the
  // rows of real tokens are compared, in order.
  const Tensor ref_pad_t = oracle.get("mid.prefix_pad_mask");
  const std::vector<float> ref_pad = ref_pad_t.to_f32();
  const Captured& our_pad = captured.at("mid.prefix_pad_mask");
  int compared = 0;
  for (const std::string& name : oracle.names()) {
    auto it = captured.find(name);
    if (it == captured.end() || name == "mid.prefix_pad_mask") continue;
    const Tensor ref = oracle.get(name);
    std::vector<float> want = ref.to_f32(), got = it->second.values;
    const bool prefix = name == "mid.prefix_embs" || name.rfind("mid.prefix_k.", 0) == 0 || name.rfind("mid.prefix_v.", 0) == 0;
    if (prefix) {
      std::vector<int64_t> n_want, n_got;
      want = real_rows(want, ref_pad, ref.dim(0), ref.dim(1), &n_want);
      got = real_rows(got, our_pad.values, our_pad.shape[0], our_pad.shape[1], &n_got);
      ASSERT_EQ(n_want, n_got) << name << ": real prefix tokens per item differ";
    } else {
      ASSERT_EQ(it->second.shape, ref.shape) << name;
    }
    const double diff = max_abs_diff(got, want);
    std::printf("  %-44s %-20s %12.3e\n", name.c_str(), shape_str(ref.shape).c_str(), diff);
    EXPECT_LE(diff, tolerance(name, want)) << name;
    ++compared;
  }
  EXPECT_GE(compared, 9) << "too few intermediates were compared";
  ASSERT_TRUE(captured.count("out.actions_normalized"));
}

// bf16 and fp16 are reduced-precision modes: their error against upstream fp32 is measured and bounded, not hidden.
void expect_half_precision_bounded(const std::string& name, cpu::Precision precision) {
  const SafeTensorsFile oracle =
      SafeTensorsFile::open((fs::path(TETHER_FIXTURES_DIR) / name / "oracle.safetensors").string());
  const auto captured = run_case(name, precision);
  const std::vector<float> want = oracle.get("out.actions_normalized").to_f32();
  const double diff = max_abs_diff(captured.at("out.actions_normalized").values, want);
  std::printf("  [%s] %s out.actions_normalized max |diff| %.3e (max |value| %.3f)\n", name.c_str(),
              cpu::precision_name(precision), diff, max_abs(want));
  EXPECT_LT(diff, 0.05 * std::max(1.0, max_abs(want)));
  EXPECT_GT(diff, 0.0) << "the reduced precision gave exactly the fp32 result: is it running at all?";
}

TEST_P(PiParity, Bf16ErrorIsBounded) { expect_half_precision_bounded(GetParam(), cpu::Precision::bf16); }
TEST_P(PiParity, Fp16ErrorIsBounded) { expect_half_precision_bounded(GetParam(), cpu::Precision::fp16); }

std::string test_name(const ::testing::TestParamInfo<std::string>& info) {
  std::string s = info.param;
  for (char& c : s)
    if (c == '/') c = '_';
  return s;
}

INSTANTIATE_TEST_SUITE_P(Fixtures, PiParity, ::testing::ValuesIn(cases()), test_name);

// use_relative_actions (the cam1_relative cases, compared with upstream above): the policy says which columns take the
// state, and takes a real-time-chunking leftover, re-anchored on the request's state (its values against lerobot's
// rollout: tests/policy/test_rtc_oracle.cpp).
TEST(PiRelativeActions, ColumnsAreNamedAndRtcIsReanchored) {
  for (const char* name : {"pi0/cam1_relative", "pi05/cam1_relative"}) {
    use_paligemma_hub();
    const fs::path dir = fs::path(TETHER_FIXTURES_DIR) / name;
    auto policy = policy::Policy::load((dir / "checkpoint").string());
    const auto& spec = policy->spec();
    EXPECT_TRUE(spec.relative_actions) << name;
    EXPECT_TRUE(spec.relative_rtc_reanchored) << name;
    EXPECT_FALSE(spec.rtc_refused_for_relative()) << name;
    EXPECT_TRUE(policy->output_normalizer().has_relative()) << name;
    std::string described;
    for (const auto& line : policy->output_normalizer().describe()) described += line + "\n";
    const std::string first = std::string(name) == "pi0/cam1_relative" ? "shoulder_pan, shoulder_lift, elbow" : "j0, j1";
    EXPECT_NE(described.find("action '" + first + "': relative to the state"), std::string::npos) << described;
    policy::Observation o = policy::synthetic_observation(spec);
    o.rtc = policy::Observation::Rtc{};
    o.rtc->prev_actions.assign(std::size_t(spec.action_dim * 2), 0.5f);
    EXPECT_EQ(policy->predict({o}).items.size(), 1u) << name;
  }
}

TEST(PiParityFixtures, Present) {
  int pi0 = 0, pi05 = 0, fluxvla = 0;
  for (const auto& c : cases()) (c.rfind("pi05/", 0) == 0 ? pi05 : c.rfind("pi05_fluxvla/", 0) == 0 ? fluxvla : pi0)++;
  EXPECT_GE(pi0, 4) << "pi0 fixtures missing under tests/fixtures/pi0";
  EXPECT_GE(pi05, 4) << "pi05 fixtures missing under tests/fixtures/pi05";
  EXPECT_GE(fluxvla, 2) << "FluxVLA fixtures missing under tests/fixtures/pi05_fluxvla";
}

}  // namespace
