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

namespace {

// A lerobot checkpoint's pipelines with relative actions: `relative` is the preprocessor's relative_actions_processor
// config (null: no such step), placed after the normalizer when `after_normalizer`; `absolute` the postprocessor's
// absolute_actions_processor enabled flag (null: no such step). State 4 wide, action 3 wide unless given.
struct RelativeCase {
  Json relative = Json{{"enabled", true}, {"exclude_joints", {"gripper"}}, {"action_names", nullptr}};
  Json absolute = true;
  bool after_normalizer = false;
  int64_t state_dim = 4, action_dim = 3;
};

fs::path write_relative_checkpoint(const std::string& name, const RelativeCase& c, Json& config) {
  const fs::path dir = tether::testing::scratch_dir() / "relative" / name;
  fs::create_directories(dir);
  Json pre = Json::array(), post = Json::array();
  const Json normalizer = {{"registry_name", "normalizer_processor"}, {"config", Json::object()}};
  if (c.after_normalizer) pre.push_back(normalizer);
  if (!c.relative.is_null()) pre.push_back({{"registry_name", "relative_actions_processor"}, {"config", c.relative}});
  if (!c.after_normalizer) pre.push_back(normalizer);
  post.push_back({{"registry_name", "unnormalizer_processor"}, {"config", Json::object()}});
  if (!c.absolute.is_null())
    post.push_back({{"registry_name", "absolute_actions_processor"}, {"config", {{"enabled", c.absolute}}}});
  std::ofstream(dir / "policy_preprocessor.json") << Json{{"name", "policy_preprocessor"}, {"steps", pre}}.dump();
  std::ofstream(dir / "policy_postprocessor.json") << Json{{"name", "policy_postprocessor"}, {"steps", post}}.dump();
  config = {{"type", "pi0"},
            {"input_features", {{"observation.state", {{"type", "STATE"}, {"shape", {c.state_dim}}}}}},
            {"output_features", {{"action", {{"type", "ACTION"}, {"shape", {c.action_dim}}}}}}};
  return dir;
}

std::vector<models::RelativeAction> relative_of(const std::string& name, const RelativeCase& c,
                                                std::vector<std::string>* warnings = nullptr) {
  Json config;
  const fs::path dir = write_relative_checkpoint(name, c, config);
  std::vector<std::string> ignored;
  return models::lerobot::read_relative_actions(dir.string(), config, warnings ? *warnings : ignored);
}

}  // namespace

// lerobot's RelativeActionsProcessorStep mask: every column converts unless both exclude_joints and action_names are
// given; a name is excluded when a token (case-insensitive) equals it or is part of it; columns past the names convert.
TEST(LerobotRelativeActions, ColumnsFollowTheExcludedNames) {
  RelativeCase all;  // exclude_joints without action_names: every column
  auto groups = relative_of("all", all);
  ASSERT_EQ(groups.size(), 1u);
  EXPECT_EQ(groups[0].action_offset, 0);
  EXPECT_EQ(groups[0].state_offset, 0);
  EXPECT_EQ(groups[0].dim, 3);
  EXPECT_EQ(groups[0].kind, models::RelativeAction::Kind::joint);

  RelativeCase named;
  named.action_dim = 4;
  named.relative["exclude_joints"] = {"GRIPPER", "", nullptr, 0};  // falsy tokens are skipped, as Python's `if name`
  named.relative["action_names"] = {"shoulder", "left_Gripper", "elbow_0"};  // the 4th column has no name: converts
  groups = relative_of("named", named);
  ASSERT_EQ(groups.size(), 2u);
  EXPECT_EQ(groups[0].action_offset, 0);
  EXPECT_EQ(groups[0].dim, 1);
  EXPECT_EQ(groups[0].name, "shoulder");
  EXPECT_EQ(groups[1].action_offset, 2);
  EXPECT_EQ(groups[1].state_offset, 2);
  EXPECT_EQ(groups[1].dim, 2);

  RelativeCase none_named = named;  // only empty tokens: every column
  none_named.relative["exclude_joints"] = {"", false};
  groups = relative_of("none_named", none_named);
  ASSERT_EQ(groups.size(), 1u);
  EXPECT_EQ(groups[0].dim, 4);

  // The whole chain: unnormalised actions plus the state's converted columns.
  const models::NormalizationSpec spec{{}, 1e-8f, relative_of("named_chain", named)};
  std::vector<float> actions = {1, 2, 3, 4, 10, 20, 30, 40};
  Normalizer(spec).to_absolute(actions.data(), 2, 4, {0.5f, 0.25f, -1, 8});
  EXPECT_EQ(actions, (std::vector<float>{1.5f, 2, 2, 12, 10.5f, 20, 29, 48}));
}

TEST(LerobotRelativeActions, OnlyAnEnabledAbsoluteStepConverts) {
  RelativeCase off;
  off.absolute = false;
  std::vector<std::string> warnings;
  EXPECT_TRUE(relative_of("off", off, &warnings).empty());
  ASSERT_EQ(warnings.size(), 1u);  // trained relative, answered as predicted
  EXPECT_NE(warnings[0].find("does not make them absolute"), std::string::npos) << warnings[0];

  RelativeCase absent;
  absent.absolute = nullptr;
  absent.relative["enabled"] = false;
  warnings.clear();
  EXPECT_TRUE(relative_of("absent", absent, &warnings).empty());
  EXPECT_TRUE(warnings.empty());
}

// Where lerobot fails at every inference (or would add a normalised state), loading fails and names the file.
TEST(LerobotRelativeActions, UnusablePipelinesAreRefused) {
  auto refused = [](const std::string& name, const RelativeCase& c, const std::string& words) {
    try {
      relative_of(name, c);
      ADD_FAILURE() << name << ": loaded";
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find(words), std::string::npos) << e.what();
    }
  };
  RelativeCase unpaired;
  unpaired.relative = nullptr;
  refused("unpaired", unpaired, "no relative_actions_processor");
  RelativeCase late;
  late.after_normalizer = true;
  refused("late", late, "runs after normalizer_processor");
  RelativeCase narrow;
  narrow.state_dim = 2;
  refused("narrow", narrow, "the state has 2 values and the action 3");
}
