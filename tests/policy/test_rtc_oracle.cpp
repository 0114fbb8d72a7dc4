// Real-time chunking against upstream: lerobot's SmolVLA, pi0 and pi0.5 with their RTCProcessor
// (tools/oracle/rtc_oracle.py, pi_rtc_oracle.py) on one fixture checkpoint each, for several
// delay/horizon/schedule/weight settings, and pi0 / pi0.5 with relative actions re-anchored as lerobot's rollout does.
// Reports max |diff| per setting.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>

#include "core/safetensors.h"
#include "policy/policy.h"

using namespace tether;
namespace fs = std::filesystem;

namespace {

// The RTC fixture and the parity case whose checkpoint and inputs it ran on.
struct RtcFixture {
  const char* rtc;
  const char* source;
};
const RtcFixture kFixtures[] = {
    {"smolvla_rtc", "smolvla/cam1_stats"},          {"pi0_rtc", "pi0/cam2_bf16"},
    {"pi05_rtc", "pi05/cam2_bf16"},                 {"pi0_rtc_relative", "pi0/cam1_relative"},
    {"pi05_rtc_relative", "pi05/cam1_relative"}};

// pi0's PaliGemma tokenizer: the oracle's stand-in, in a hub cache under its real repo id.
const bool kHubCacheSet = [] {
  ::setenv("HF_HUB_CACHE", (fs::path(TETHER_FIXTURES_DIR) / "paligemma_hub").c_str(), 1);
  return true;
}();

double max_abs_diff(const std::vector<float>& a, const std::vector<float>& b) {
  double m = 0;
  for (std::size_t i = 0; i < a.size(); ++i) m = std::max(m, std::fabs(double(a[i]) - double(b[i])));
  return m;
}

std::vector<float> slice(const std::vector<float>& all, int64_t b, int64_t per_item) {
  return {all.begin() + b * per_item, all.begin() + (b + 1) * per_item};
}

}  // namespace

class RtcOracle : public ::testing::TestWithParam<RtcFixture> {};

TEST_P(RtcOracle, MatchesLerobotsRtcProcessor) {
  const fs::path kSource = fs::path(TETHER_FIXTURES_DIR) / GetParam().source;
  const fs::path kOracle = fs::path(TETHER_FIXTURES_DIR) / GetParam().rtc / "oracle.safetensors";
  ASSERT_TRUE(fs::exists(kOracle)) << kOracle << " missing: tools/oracle/regenerate.sh writes it";
  const SafeTensorsFile source = SafeTensorsFile::open((kSource / "oracle.safetensors").string());
  const SafeTensorsFile oracle = SafeTensorsFile::open(kOracle.string());
  auto policy = policy::Policy::load((kSource / "checkpoint").string());
  const auto& spec = policy->spec();
  const Json cameras = Json::parse(source.metadata().at("cameras"));
  const Json files = Json::parse(source.metadata().at("input_files"));
  const Json instructions = Json::parse(source.metadata().at("instructions"));
  // A relative-actions fixture moves the robot between the two chunks: its own input.state is the new one.
  const Tensor state = oracle.contains("input.state") ? oracle.get("input.state") : source.get("input.state");
  const std::vector<float> states = state.to_f32(), noise = oracle.get("input.noise").to_f32();
  const Tensor prev = oracle.get("input.prev_actions");
  const std::vector<float> prev_actions = prev.to_f32();
  const int64_t B = state.dim(0), C = spec.chunk_size, A = spec.action_dim;

  std::vector<policy::Observation> batch(static_cast<std::size_t>(B));
  for (int64_t b = 0; b < B; ++b) {
    policy::Observation& o = batch[b];
    o.state = slice(states, b, state.dim(1));
    o.instruction = instructions.at(b).get<std::string>();
    o.noise = slice(noise, b, C * spec.max_action_dim);
    for (const auto& cam : cameras) {
      const std::string key = cam.get<std::string>();
      o.images[key] = vision::load_image((kSource / "inputs" / files.at(key).at(b).get<std::string>()).string());
    }
  }
  std::vector<float> normalized;
  policy->set_debug_hook([&](const std::string& name, const Tensor& t) {
    if (name == "out.actions_normalized") normalized = t.to_f32();
  });

  policy->predict(batch);
  const double plain = max_abs_diff(normalized, oracle.get("out.no_rtc.actions_normalized").to_f32());
  std::printf("[ rtc oracle ] %s %-14s normalised max |diff| %.2e\n", GetParam().rtc, "no RTC", plain);
  EXPECT_LT(plain, 1e-5);

  for (const auto& c : Json::parse(oracle.metadata().at("cases"))) {
    const std::string name = c.at("name").get<std::string>();
    for (int64_t b = 0; b < B; ++b)
      batch[b].rtc = policy::Observation::Rtc{
          .prev_actions = slice(prev_actions, b, prev.dim(1) * A),
          .inference_delay = c.at("inference_delay").get<int>(),
          .execution_horizon = c.at("execution_horizon").get<int>(),
          .max_guidance_weight = c.at("max_guidance_weight").get<float>(),
          .schedule = models::parse_rtc_schedule(c.at("schedule").get<std::string>())};
    const policy::Prediction p = policy->predict(batch);
    std::vector<float> actions;
    for (const auto& item : p.items) actions.insert(actions.end(), item.actions.begin(), item.actions.end());
    const std::vector<float> want = oracle.get("out." + name + ".actions").to_f32();
    double scale = 1.0;
    for (float v : want) scale = std::max(scale, double(std::fabs(v)));
    const double norm_diff = max_abs_diff(normalized, oracle.get("out." + name + ".actions_normalized").to_f32());
    const double robot_diff = max_abs_diff(actions, want);
    std::printf("[ rtc oracle ] %s %-14s normalised max |diff| %.2e, robot units %.2e (max |action| %.1f)\n",
                GetParam().rtc, name.c_str(), norm_diff, robot_diff, scale);
    // The leftover goes robot units -> normalised through float32 stats, one rounding more than upstream's path.
    EXPECT_LT(norm_diff, 1e-5) << name;
    EXPECT_LT(robot_diff, 1e-5 * scale) << name;
  }
}

INSTANTIATE_TEST_SUITE_P(Families, RtcOracle, ::testing::ValuesIn(kFixtures),
                         [](const auto& info) { return std::string(info.param.rtc); });
