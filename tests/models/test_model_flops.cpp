// The flops a model reports for a forward pass (summed from its blocks' own counts, for `tether bench`'s GFLOP/s)
// equal what the backend counted while running it, for a batch of different prompt lengths, with and without
// adaptive early stops.
#include <gtest/gtest.h>

#include <filesystem>

#include "core/json_util.h"
#include "models/family.h"
#include "vision/image.h"

using namespace tether;
namespace fs = std::filesystem;

namespace {

void expect_reported_equals_counted(const std::string& fixture, float adaptive_threshold) {
  const fs::path dir = fs::path(TETHER_FIXTURES_DIR) / "smolvla" / fixture / "checkpoint";
  models::LoadOptions options;
  options.backend = backend::make_backend("cpu");
  auto model = models::load_checkpoint(dir, options).model;
  const models::ModelSpec& spec = model->spec();
  models::ModelInput in;
  const vision::Image image =
      vision::load_image((fs::path(TETHER_FIXTURES_DIR) / "smolvla/cam1_stats/inputs/camera1_0.png").string());
  in.images[spec.cameras.front()] = image;  // further cameras missing: their masked or dropped slots count too
  in.state.assign(std::size_t(spec.state_dim), 0.25f);
  in.denoise.adaptive_threshold = adaptive_threshold;
  std::vector<models::ModelInput> batch = {in, in};
  batch[0].instruction = "stack the blocks";
  batch[1].instruction = "put the red cube in the bowl on the left, then push the drawer closed";
  batch[1].seed = 9;
  const double before = options.backend->flops().total();
  const models::ModelOutput out = model->predict(batch);
  const double counted = options.backend->flops().total() - before;
  std::printf("[ flops      ] %s (adaptive %g): %.4g reported, %.4g counted\n", fixture.c_str(), adaptive_threshold,
              out.flops, counted);
  EXPECT_GT(out.flops, 0);
  EXPECT_DOUBLE_EQ(out.flops, counted);
}

}  // namespace

TEST(ModelFlops, ReportedEqualsCountedByTheBackend) {
  expect_reported_equals_counted("cam1_stats", 0);
  expect_reported_equals_counted("cam3_stats", 0);
  expect_reported_equals_counted("cam2_bf16_fewer_expert_layers", 0);
}

TEST(ModelFlops, AdaptiveStopsCountTheStepsRun) { expect_reported_equals_counted("cam3_stats", 1e9f); }
