// The batching guarantee at every precision and for every family: an item's chunk does not depend on its batch-mates
// (their number, their prompt lengths, their cameras). Exact on the fixed-order paths; the native bf16 GEMM (oneDNN)
// is bounded and reported.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <map>
#include <string>
#include <tuple>

#include "backend/cpu/packed_linear.h"
#include "policy/policy.h"
#include "vision/image.h"

using namespace tether;

namespace {

// The bundled demo (SmolVLA) and a tiny fixture checkpoint of each other family.
const std::vector<std::string>& checkpoints() {
  static const std::vector<std::string> all = [] {
    std::vector<std::string> out = {std::string(TETHER_SOURCE_DIR) + "/models/demo/smolvla-demo"};
    for (const char* c : {"pi0/cam3_nostats_trunc", "pi05/cam3_nostats_trunc"}) {
      const std::filesystem::path dir = std::filesystem::path(TETHER_FIXTURES_DIR) / c / "checkpoint";
      if (std::filesystem::exists(dir)) out.push_back(dir.string());
    }
    // pi0's PaliGemma tokenizer: the oracle's stand-in, in a hub cache under its real repo id.
    ::setenv("HF_HUB_CACHE", (std::filesystem::path(TETHER_FIXTURES_DIR) / "paligemma_hub").c_str(), 1);
    return out;
  }();
  return all;
}

policy::Policy& load(const std::string& dir, cpu::Precision precision) {
  static std::map<std::pair<std::string, cpu::Precision>, std::unique_ptr<policy::Policy>> loaded;
  auto& p = loaded[{dir, precision}];
  if (!p) {
    models::LoadOptions o;
    o.precision = precision;
    p = policy::Policy::load(dir, o);
  }
  return *p;
}

// Every real camera shows the demo image unless `cameras` limits them to the first few.
policy::Observation observation(const policy::Policy& p, uint64_t seed, const std::string& instruction,
                                std::size_t cameras = 99) {
  policy::Observation o;
  const auto& spec = p.spec();
  for (const auto& cam : spec.cameras) {
    if (o.images.size() >= cameras) break;
    if (std::find(spec.synthetic_cameras.begin(), spec.synthetic_cameras.end(), cam) != spec.synthetic_cameras.end())
      continue;
    o.images[cam] = vision::load_image(std::string(TETHER_SOURCE_DIR) + "/models/demo/sample.png");
  }
  for (int64_t i = 0; i < spec.state_dim; ++i) o.state.push_back(0.1f * float((i % 7) - 3));
  o.instruction = instruction;
  o.seed = seed;
  return o;
}

std::string family_of(const std::string& dir) {
  return dir.find("/pi05/") != std::string::npos ? "pi05" : dir.find("/pi0/") != std::string::npos ? "pi0" : "smolvla";
}

}  // namespace

class BatchInvariance : public ::testing::TestWithParam<std::tuple<std::string, cpu::Precision>> {};

TEST_P(BatchInvariance, AnItemsChunkIgnoresItsBatchMates) {
  const auto& [dir, precision] = GetParam();
  policy::Policy& p = load(dir, precision);
  const policy::Observation item = observation(p, 31, "pick up the red cube");
  const std::vector<float> alone = p.predict({item}).items.at(0).actions;
  // Batch-mates of another prompt length (the prefix is padded to the longest), another count, and one with a
  // camera missing (masked where the model has several).
  const std::vector<policy::Observation> batch = {
      observation(p, 32, "open the top drawer of the cabinet, then put the bowl on the plate inside it"),
      item, observation(p, 33, "stack", 1), observation(p, 34, "pick up the red cube")};
  const std::vector<float> batched = p.predict(batch).items.at(1).actions;
  double diff = 0, scale = 0;
  for (std::size_t i = 0; i < alone.size(); ++i) {
    diff = std::max(diff, std::fabs(double(alone[i]) - double(batched[i])));
    scale = std::max(scale, std::fabs(double(alone[i])));
  }
  std::printf("[ batching   ] %s %s (%s): max |batched - alone| %.3g (max |action| %.3g)\n", family_of(dir).c_str(),
              cpu::precision_name(precision), cpu::compute_mode(precision), diff, scale);
  if (cpu::linear_path(precision) == cpu::LinearPath::onednn_bf16 ||
      cpu::linear_path(precision) == cpu::LinearPath::onednn_f32) {
    // oneDNN blocks by row count, so its last bits follow the batch: bounded (bf16 rounding dominates).
    EXPECT_LT(diff, 1e-2 * scale);
  } else {
    EXPECT_EQ(batched, alone) << "a batch-mate changed the chunk";
  }
}

INSTANTIATE_TEST_SUITE_P(Precisions, BatchInvariance,
                         ::testing::Combine(::testing::ValuesIn(checkpoints()),
                                            ::testing::Values(cpu::Precision::fp32, cpu::Precision::bf16,
                                                              cpu::Precision::fp16)),
                         [](const auto& info) {
                           return family_of(std::get<0>(info.param)) + "_" +
                                  cpu::precision_name(std::get<1>(info.param));
                         });
