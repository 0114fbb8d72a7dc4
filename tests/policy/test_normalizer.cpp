// Normaliser: lerobot's processor files read (models/lerobot), its formulas per mode, the degenerate-range guard, and missing stats handled as upstream.
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <unistd.h>

#include "core/safetensors.h"
#include "models/lerobot/checkpoint.h"
#include "policy/normalizer.h"
#include "scratch_dir.h"

using namespace tether;
using namespace tether::policy;
namespace fs = std::filesystem;

namespace {

fs::path make_checkpoint(const std::string& name, const std::string& mode, const std::map<std::string, std::vector<float>>& stats) {
  fs::path dir = tether::testing::scratch_dir() / "norm" / name;
  fs::create_directories(dir);
  Json features = {{"observation.state", {{"type", "STATE"}, {"shape", {2}}}}, {"action", {{"type", "ACTION"}, {"shape", {2}}}}};
  Json step = {{"registry_name", "normalizer_processor"},
               {"config", {{"eps", 1e-8}, {"features", features}, {"norm_map", {{"STATE", mode}, {"ACTION", mode}}}}}};
  if (!stats.empty()) {
    std::map<std::string, Tensor> tensors;
    for (const auto& [k, v] : stats) tensors[k] = Tensor::from_f32({int64_t(v.size())}, v);
    write_safetensors((dir / "stats.safetensors").string(), tensors);
    step["state_file"] = "stats.safetensors";
  }
  std::ofstream(dir / "policy_preprocessor.json") << Json{{"name", "policy_preprocessor"}, {"steps", {step}}}.dump();
  return dir;
}

Json config() { return {{"type", "smolvla"}}; }

}  // namespace

TEST(Normalizer, MeanStdForwardAndInverse) {
  auto dir = make_checkpoint("meanstd", "MEAN_STD",
                             {{"observation.state.mean", {1.f, -2.f}}, {"observation.state.std", {2.f, 0.5f}},
                              {"action.mean", {0.f, 10.f}}, {"action.std", {1.f, 4.f}}});
  std::vector<std::string> warnings;
  Normalizer n = Normalizer(models::lerobot::read_pipeline_normalization(dir.string(), "policy_preprocessor.json", "normalizer_processor", config(), warnings));
  EXPECT_TRUE(warnings.empty());
  std::vector<float> s = {3.f, -1.f, 1.f, -2.f};  // two rows
  n.normalize("observation.state", s.data(), 4);
  EXPECT_FLOAT_EQ(s[0], (3.f - 1.f) / (2.f + 1e-8f));
  EXPECT_FLOAT_EQ(s[1], (-1.f + 2.f) / (0.5f + 1e-8f));
  EXPECT_FLOAT_EQ(s[2], 0.f);
  std::vector<float> a = {1.f, -1.f};
  n.unnormalize("action", a.data(), 2);
  EXPECT_FLOAT_EQ(a[0], 1.f);
  EXPECT_FLOAT_EQ(a[1], 6.f);
}

TEST(Normalizer, MinMaxWithDegenerateRange) {
  auto dir = make_checkpoint("minmax", "MIN_MAX", {{"observation.state.min", {0.f, 5.f}}, {"observation.state.max", {10.f, 5.f}}});
  std::vector<std::string> warnings;
  Normalizer n = Normalizer(models::lerobot::read_pipeline_normalization(dir.string(), "policy_preprocessor.json", "normalizer_processor", config(), warnings));
  std::vector<float> s = {5.f, 5.f};
  n.normalize("observation.state", s.data(), 2);
  EXPECT_FLOAT_EQ(s[0], 0.f);
  EXPECT_FLOAT_EQ(s[1], -1.f);  // min == max: the denominator becomes eps, the value maps to -1
  n.unnormalize("observation.state", s.data(), 2);
  EXPECT_FLOAT_EQ(s[0], 5.f);
  // The action has MIN_MAX configured but no stats: left alone, with a warning.
  ASSERT_EQ(warnings.size(), 1u);
  EXPECT_NE(warnings[0].find("action"), std::string::npos);
  std::vector<float> a = {0.25f, 7.f};
  n.unnormalize("action", a.data(), 2);
  EXPECT_EQ(a, (std::vector<float>{0.25f, 7.f}));
}

TEST(Normalizer, NoStatsIsIdentityWithWarnings) {
  auto dir = make_checkpoint("nostats", "MEAN_STD", {});
  std::vector<std::string> warnings;
  Normalizer n = Normalizer(models::lerobot::read_pipeline_normalization(dir.string(), "policy_preprocessor.json", "normalizer_processor", config(), warnings));
  EXPECT_EQ(warnings.size(), 2u);
  std::vector<float> s = {1.5f, -3.f};
  n.normalize("observation.state", s.data(), 2);
  EXPECT_EQ(s, (std::vector<float>{1.5f, -3.f}));
}

TEST(Normalizer, QuantilesAndWidthMismatch) {
  auto dir = make_checkpoint("quant", "QUANTILES", {{"observation.state.q01", {-1.f, 0.f}}, {"observation.state.q99", {1.f, 4.f}}});
  std::vector<std::string> warnings;
  Normalizer n = Normalizer(models::lerobot::read_pipeline_normalization(dir.string(), "policy_preprocessor.json", "normalizer_processor", config(), warnings));
  std::vector<float> s = {0.f, 1.f};
  n.normalize("observation.state", s.data(), 2);
  EXPECT_FLOAT_EQ(s[0], 0.f);
  EXPECT_FLOAT_EQ(s[1], -0.5f);
  n.unnormalize("observation.state", s.data(), 2);
  EXPECT_FLOAT_EQ(s[1], 1.f);
  std::vector<float> bad = {1.f, 2.f, 3.f};
  EXPECT_THROW(n.normalize("observation.state", bad.data(), 3), Error);
}

TEST(Normalizer, UnknownModeIsRejected) {
  auto dir = make_checkpoint("badmode", "ZSCORE_PLUS", {});
  std::vector<std::string> warnings;
  EXPECT_THROW(Normalizer(models::lerobot::read_pipeline_normalization(dir.string(), "policy_preprocessor.json", "normalizer_processor", config(), warnings)), Error);
}

// GR00T's relative action groups made absolute: a NON_EEF group adds the state; an EEF group in xyz+rot6d composes
// T_state * T_action (lerobot's relative_eef_to_absolute). Rotations about z make the expected poses exact.
TEST(Normalizer, RelativeGroupsAreMadeAbsoluteAgainstTheState) {
  models::NormalizationSpec spec;
  spec.relative = {{models::RelativeAction::Kind::eef_xyz_rot6d, "eef", 0, 0, 9},
                   {models::RelativeAction::Kind::joint, "joints", 9, 10, 2}};
  const Normalizer n(spec);
  const double a = 0.3, b = -0.5;
  // State: pose at (1, 2, 3) rotated by a about z; a state group in between (x) that no action reads; joints (5, 6).
  const std::vector<float> state = {1, 2, 3, float(std::cos(a)), float(-std::sin(a)), 0, float(std::sin(a)),
                                    float(std::cos(a)), 0, 9, 5, 6};
  // Two rows: the identity (the state's own pose), then a translation (0.5, 0, 0) with a rotation b about z; the
  // second row's rot6d is scaled by 2 (Gram-Schmidt normalises it).
  std::vector<float> actions = {0, 0, 0, 1, 0, 0, 0, 1, 0, 0.25f, -0.5f,
                                0.5f, 0, 0, float(2 * std::cos(b)), float(-2 * std::sin(b)), 0, float(2 * std::sin(b)),
                                float(2 * std::cos(b)), 0, 1, 1};
  n.to_absolute(actions.data(), 2, 11, state);
  for (int k = 0; k < 9; ++k) EXPECT_NEAR(actions[std::size_t(k)], state[std::size_t(k)], 1e-7) << k;
  EXPECT_FLOAT_EQ(actions[9], 5.25f);
  EXPECT_FLOAT_EQ(actions[10], 5.5f);
  const float* r = actions.data() + 11;
  // Translation: state + R(a) * (0.5, 0, 0); rotation: R(a + b).
  EXPECT_NEAR(r[0], 1 + 0.5 * std::cos(a), 1e-6);
  EXPECT_NEAR(r[1], 2 + 0.5 * std::sin(a), 1e-6);
  EXPECT_NEAR(r[2], 3, 1e-6);
  const double c = std::cos(a + b), s = std::sin(a + b);
  const double want[6] = {c, -s, 0, s, c, 0};
  for (int k = 0; k < 6; ++k) EXPECT_NEAR(r[3 + k], want[k], 1e-6) << k;
  EXPECT_FLOAT_EQ(r[9], 6);
  EXPECT_FLOAT_EQ(r[10], 7);
  EXPECT_TRUE(n.has_relative());
  EXPECT_FALSE(Normalizer(models::NormalizationSpec{}).has_relative());
}
