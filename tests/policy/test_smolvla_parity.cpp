// SmolVLA parity: every oracle fixture case is run through Tether end to end (image files, robot-unit state,
// instruction, the oracle's noise) and compared with upstream lerobot, intermediates included.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <map>

#include "core/safetensors.h"
#include "policy/policy.h"

using namespace tether;
namespace fs = std::filesystem;

namespace {

struct Captured {
  Shape shape;
  std::vector<float> values;
};

std::vector<std::string> cases() {
  std::vector<std::string> out;
  const fs::path root = fs::path(TETHER_FIXTURES_DIR) / "smolvla";
  if (!fs::exists(root)) return out;
  for (const auto& e : fs::directory_iterator(root))
    if (fs::exists(e.path() / "oracle.safetensors")) out.push_back(e.path().filename().string());
  std::sort(out.begin(), out.end());
  return out;
}

double max_abs_diff(const std::vector<float>& a, const std::vector<float>& b) {
  double m = 0;
  for (std::size_t i = 0; i < a.size(); ++i) m = std::max(m, std::fabs(double(a[i]) - double(b[i])));
  return m;
}

// Tolerances, fp32 end to end: preprocessing is exact up to 1e-6; the normalised action chunk (the model's
// output) must be within 1e-5; robot-unit actions are that chunk scaled by the stats, so their bound scales with
// their magnitude (1e-5 relative: a float32 ulp at 100 is already 7.6e-6). Intermediates deep in the network
// carry GEMM summation-order noise and get 1e-4.
double tolerance(const std::string& name, const std::vector<float>& ref) {
  if (name.rfind("pre.", 0) == 0) return 1e-6;
  if (name == "out.actions") {
    double scale = 1.0;
    for (float v : ref) scale = std::max(scale, double(std::fabs(v)));
    return 1e-5 * scale;
  }
  if (name.rfind("out.", 0) == 0) return 1e-5;
  return 1e-4;
}

// Runs one fixture case end to end through Tether at `precision`; returns what it captured, by fixture name.
std::map<std::string, Captured> run_case(const std::string& name, cpu::Precision precision) {
  const fs::path dir = fs::path(TETHER_FIXTURES_DIR) / "smolvla" / name;
  const SafeTensorsFile oracle = SafeTensorsFile::open((dir / "oracle.safetensors").string());
  const Json cameras = Json::parse(oracle.metadata().at("cameras"));
  const Json instructions = Json::parse(oracle.metadata().at("instructions"));
  const Json files = Json::parse(oracle.metadata().at("input_files"));
  models::LoadOptions options;
  options.precision = precision;
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
      o.images[key] = vision::load_image((dir / "inputs" / files.at(key).at(b).get<std::string>()).string());
      // The decoded file must be exactly the pixels upstream saw.
      const Tensor expected = oracle.get("input.image." + key);
      const auto& img = o.images[key];
      EXPECT_EQ((Shape{img.height, img.width, 3}), (Shape{expected.dim(1), expected.dim(2), 3})) << key;
      EXPECT_EQ(std::memcmp(img.rgb.data(), expected.as<uint8_t>() + b * img.rgb.size(), img.rgb.size()), 0)
          << key << " item " << b << " decodes differently from PIL";
    }
  }

  std::map<std::string, Captured> captured;
  policy->set_debug_hook([&](const std::string& name, const Tensor& t) { captured[name] = {t.shape, t.to_f32()}; });
  const policy::Prediction pred = policy->predict(batch);

  Captured actions{{B, spec.chunk_size, spec.action_dim}, {}};
  for (const auto& item : pred.items) actions.values.insert(actions.values.end(), item.actions.begin(), item.actions.end());
  captured["out.actions"] = actions;

  return captured;
}

class SmolVLAParity : public ::testing::TestWithParam<std::string> {};

TEST_P(SmolVLAParity, MatchesUpstream) {
  const fs::path dir = fs::path(TETHER_FIXTURES_DIR) / "smolvla" / GetParam();
  const SafeTensorsFile oracle = SafeTensorsFile::open((dir / "oracle.safetensors").string());
  const std::map<std::string, Captured> captured = run_case(GetParam(), cpu::Precision::fp32);
  std::printf("  %-40s %-16s %12s\n", ("[" + GetParam() + "]").c_str(), "shape", "max |diff|");
  int compared = 0;
  for (const std::string& name : oracle.names()) {
    auto it = captured.find(name);
    if (it == captured.end()) continue;
    const Tensor ref = oracle.get(name);
    ASSERT_EQ(it->second.shape, ref.shape) << name;
    const std::vector<float> want = ref.to_f32();
    const double diff = max_abs_diff(it->second.values, want);
    std::printf("  %-40s %-16s %12.3e\n", name.c_str(), shape_str(ref.shape).c_str(), diff);
    EXPECT_LE(diff, tolerance(name, want)) << name;
    ++compared;
  }
  EXPECT_GE(compared, 10) << "too few intermediates were compared";
  ASSERT_TRUE(captured.count("out.actions"));
}

// bf16 is a reduced-precision mode: its error against upstream fp32 is measured and bounded, not hidden.
TEST_P(SmolVLAParity, Bf16ErrorIsBounded) {
  const SafeTensorsFile oracle =
      SafeTensorsFile::open((fs::path(TETHER_FIXTURES_DIR) / "smolvla" / GetParam() / "oracle.safetensors").string());
  const auto captured = run_case(GetParam(), cpu::Precision::bf16);
  const std::vector<float> want = oracle.get("out.actions_normalized").to_f32();
  const double diff = max_abs_diff(captured.at("out.actions_normalized").values, want);
  double scale = 0;
  for (float v : want) scale = std::max(scale, double(std::fabs(v)));
  std::printf("  [%s] bf16 out.actions_normalized max |diff| %.3e (max |value| %.3f)\n", GetParam().c_str(), diff, scale);
  EXPECT_LT(diff, 0.05 * std::max(1.0, scale));
  EXPECT_GT(diff, 0.0) << "bf16 mode gave exactly the fp32 result: is it running at all?";
}

INSTANTIATE_TEST_SUITE_P(Fixtures, SmolVLAParity, ::testing::ValuesIn(cases()),
                         [](const auto& info) { return info.param; });

TEST(SmolVLAParityFixtures, Present) { EXPECT_GE(cases().size(), 4u) << "fixtures missing under tests/fixtures/smolvla"; }

}  // namespace
