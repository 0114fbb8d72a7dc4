// The batching guarantee at every precision: an item's chunk does not depend on its batch-mates (their number,
// their prompt lengths). Exact on the fixed-order paths; the native bf16 GEMM (oneDNN) is bounded and reported.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <map>
#include <string>

#include "backend/cpu/packed_linear.h"
#include "policy/policy.h"
#include "vision/image.h"

using namespace tether;

namespace {

const std::string kDemo = std::string(TETHER_SOURCE_DIR) + "/models/demo/smolvla-demo";

policy::Policy& demo(cpu::Precision precision) {
  static std::map<cpu::Precision, std::unique_ptr<policy::Policy>> loaded;
  auto& p = loaded[precision];
  if (!p) {
    models::LoadOptions o;
    o.precision = precision;
    p = policy::Policy::load(kDemo, o);
  }
  return *p;
}

policy::Observation observation(const policy::Policy& p, uint64_t seed, const std::string& instruction) {
  policy::Observation o;
  o.images[p.spec().cameras.at(0)] = vision::load_image(std::string(TETHER_SOURCE_DIR) + "/models/demo/sample.png");
  o.state = {0.1f, -0.2f, 0.3f, 0.0f, 0.5f, -0.4f};
  o.instruction = instruction;
  o.seed = seed;
  return o;
}

}  // namespace

class BatchInvariance : public ::testing::TestWithParam<cpu::Precision> {};

TEST_P(BatchInvariance, AnItemsChunkIgnoresItsBatchMates) {
  const cpu::Precision precision = GetParam();
  policy::Policy& p = demo(precision);
  const policy::Observation item = observation(p, 31, "pick up the red cube");
  const std::vector<float> alone = p.predict({item}).items.at(0).actions;
  // Batch-mates of another prompt length (the prefix is padded to the longest) and another count.
  const std::vector<policy::Observation> batch = {
      observation(p, 32, "open the top drawer of the cabinet, then put the bowl on the plate inside it"),
      item, observation(p, 33, "stack"), observation(p, 34, "pick up the red cube")};
  const std::vector<float> batched = p.predict(batch).items.at(1).actions;
  double diff = 0, scale = 0;
  for (std::size_t i = 0; i < alone.size(); ++i) {
    diff = std::max(diff, std::fabs(double(alone[i]) - double(batched[i])));
    scale = std::max(scale, std::fabs(double(alone[i])));
  }
  std::printf("[ batching   ] %s (%s): max |batched - alone| %.3g (max |action| %.3g)\n",
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
                         ::testing::Values(cpu::Precision::fp32, cpu::Precision::bf16, cpu::Precision::fp16),
                         [](const auto& info) { return std::string(cpu::precision_name(info.param)); });
