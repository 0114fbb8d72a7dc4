// `tether predict` end to end through the binary: output, reproducibility and every user error's exit code.
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>

#include "backend/cpu/packed_linear.h"
#include "cli_runner.h"
#include "core/json_util.h"
#include "core/safetensors.h"
#include "scratch_dir.h"

using namespace tether;
namespace fs = std::filesystem;

namespace {

const std::string kDemo = std::string(TETHER_SOURCE_DIR) + "/models/demo/smolvla-demo";
const std::string kImage = std::string(TETHER_SOURCE_DIR) + "/models/demo/sample.png";
const std::string kGood = kDemo + " --image front=" + kImage + " --state 0,90,90,45,0,20 --instruction 'pick up the cube'";

int lines(const std::string& s) { return int(std::count(s.begin(), s.end(), '\n')); }

}  // namespace

TEST(PredictCli, PrintsChunkAndStageLatencies) {
  const CliRun r = run_tether("predict " + kGood + " --seed 3 --json");
  ASSERT_EQ(r.code, 0) << r.err;
  const Json j = Json::parse(r.out);
  EXPECT_EQ(j["num_actions"], 50);
  EXPECT_EQ(j["action_dim"], 6);
  ASSERT_EQ(j["actions"].size(), 50u);
  EXPECT_EQ(j["actions"][0].size(), 6u);
  for (const char* stage : {"load", "preprocess", "vision", "prefix", "denoise", "postprocess", "total"})
    EXPECT_TRUE(j["latency_ms"].contains(stage)) << stage;

  const CliRun table = run_tether("predict " + kGood + " --seed 3");
  ASSERT_EQ(table.code, 0) << table.err;
  EXPECT_NE(table.out.find("action chunk: 50 x 6"), std::string::npos);
  EXPECT_NE(table.out.find("latency (ms):"), std::string::npos);
}

TEST(PredictCli, SeedMakesRunsReproducible) {
  const Json a = Json::parse(run_tether("predict " + kGood + " --seed 11 --json").out);
  const Json b = Json::parse(run_tether("predict " + kGood + " --seed 11 --json").out);
  const Json c = Json::parse(run_tether("predict " + kGood + " --seed 12 --json").out);
  EXPECT_EQ(a["actions"], b["actions"]);
  EXPECT_NE(a["actions"], c["actions"]);
}

TEST(PredictCli, Bf16ModeIsReportedAndClose) {
  const Json f32 = Json::parse(run_tether("predict " + kGood + " --seed 4 --json").out);
  const CliRun r = run_tether("predict " + kGood + " --seed 4 --json --precision bf16");
  ASSERT_EQ(r.code, 0) << r.err;
  const Json bf16 = Json::parse(r.out);
  EXPECT_EQ(f32["inference_mode"], "cpu-fp32");
  // Native bf16 GEMM where this CPU has bf16 instructions, bf16 weights widened in the kernel elsewhere.
  EXPECT_EQ(bf16["inference_mode"], std::string("cpu-") + cpu::compute_mode(cpu::Precision::bf16));
  const Json fp16 = Json::parse(run_tether("predict " + kGood + " --seed 4 --json --precision fp16").out);
  EXPECT_EQ(fp16["inference_mode"], "cpu-fp16-weights");
  double diff = 0, scale = 0;
  for (std::size_t i = 0; i < 50; ++i)
    for (std::size_t j = 0; j < 6; ++j) {
      diff = std::max(diff, std::fabs(f32["actions"][i][j].get<double>() - bf16["actions"][i][j].get<double>()));
      scale = std::max(scale, std::fabs(f32["actions"][i][j].get<double>()));
    }
  EXPECT_GT(diff, 0.0);
  EXPECT_LT(diff, 0.02 * scale);
  double diff16 = 0;
  for (std::size_t i = 0; i < 50; ++i)
    for (std::size_t j = 0; j < 6; ++j)
      diff16 = std::max(diff16, std::fabs(f32["actions"][i][j].get<double>() - fp16["actions"][i][j].get<double>()));
  EXPECT_GT(diff16, 0.0);
  EXPECT_LT(diff16, 0.02 * scale);
  EXPECT_EQ(run_tether("predict " + kGood + " --precision fp8").code, 2);
}

TEST(PredictCli, SameBitsOnEveryDispatchLevel) {
  // fp32 and the widened half-precision paths run fixed-order chains in every product, so capping the dispatch
  // (as on an older CPU) changes no bit of the chunk. Native bf16 (oneDNN) is the one path outside this.
  for (const char* precision : {"fp32", "fp16"}) {
    const std::string args = "predict " + kGood + " --seed 9 --json --precision " + precision;
    const CliRun native = run_tether(args);
    ASSERT_EQ(native.code, 0) << native.err;
    for (const char* cap : kLowerIsaCaps) {
      ::setenv("TETHER_MAX_CPU_ISA", cap, 1);
      const CliRun capped = run_tether(args);
      ::unsetenv("TETHER_MAX_CPU_ISA");
      ASSERT_EQ(capped.code, 0) << capped.err;
      EXPECT_EQ(Json::parse(capped.out)["actions"], Json::parse(native.out)["actions"]) << precision << " at " << cap;
    }
  }
  ::setenv("TETHER_MAX_CPU_ISA", "AVX9", 1);
  const CliRun bad = run_tether("predict " + kGood + " --seed 9");
  ::unsetenv("TETHER_MAX_CPU_ISA");
  EXPECT_EQ(bad.code, 2);
  EXPECT_NE(bad.err.find("TETHER_MAX_CPU_ISA='AVX9' is not one of"), std::string::npos) << bad.err;
}

TEST(PredictCli, Bf16GemmOverrideWidensOnEveryCpuAndRefusesBadValues) {
  // TETHER_BF16_GEMM=widened puts bf16 on the widened panel path whatever the CPU has, so it gives the bits of the
  // AVX2-capped run (which has no bf16 instructions); native is refused where there are no bf16 instructions.
  const std::string args = "predict " + kGood + " --seed 5 --json --precision bf16";
  ::setenv("TETHER_MAX_CPU_ISA", kLowerIsaCaps[0], 1);
  const CliRun capped = run_tether(args);
  ::setenv("TETHER_BF16_GEMM", "native", 1);
  const CliRun native_without_bf16 = run_tether(args);
  ::unsetenv("TETHER_MAX_CPU_ISA");
  ::setenv("TETHER_BF16_GEMM", "widened", 1);
  const CliRun widened = run_tether(args);
  ::setenv("TETHER_BF16_GEMM", "fastest", 1);
  const CliRun bad = run_tether(args);
  ::unsetenv("TETHER_BF16_GEMM");
  ASSERT_EQ(capped.code, 0) << capped.err;
  ASSERT_EQ(widened.code, 0) << widened.err;
  EXPECT_EQ(Json::parse(widened.out)["inference_mode"], "cpu-bf16-weights");
  EXPECT_EQ(Json::parse(widened.out)["actions"], Json::parse(capped.out)["actions"]);
  EXPECT_EQ(native_without_bf16.code, 2);
  EXPECT_NE(native_without_bf16.err.find("TETHER_BF16_GEMM=native, but this CPU runs oneDNN at"), std::string::npos)
      << native_without_bf16.err;
  EXPECT_EQ(bad.code, 2);
  EXPECT_NE(bad.err.find("TETHER_BF16_GEMM='fastest' is not one of native, widened"), std::string::npos) << bad.err;
}

TEST(PredictCli, ExplicitNoiseFile) {
  const fs::path noise = tether::testing::scratch_dir() / "noise.safetensors";
  std::vector<float> zeros(50 * 32, 0.0f);
  write_safetensors(noise.string(), {{"noise", Tensor::from_f32({1, 50, 32}, zeros)}});
  const CliRun r = run_tether("predict " + kGood + " --noise " + noise.string() + " --json");
  ASSERT_EQ(r.code, 0) << r.err;
  // The seed is ignored when noise is given: two seeds, same noise, same actions.
  const CliRun r2 = run_tether("predict " + kGood + " --noise " + noise.string() + " --seed 99 --json");
  EXPECT_EQ(Json::parse(r.out)["actions"], Json::parse(r2.out)["actions"]);
  std::vector<float> wrong(10, 0.0f);
  write_safetensors(noise.string(), {{"noise", Tensor::from_f32({10}, wrong)}});
  const CliRun bad = run_tether("predict " + kGood + " --noise " + noise.string());
  EXPECT_EQ(bad.code, 2);
  EXPECT_NE(bad.err.find("noise"), std::string::npos) << bad.err;
}

TEST(PredictCli, UserErrorsExitTwoWithOneLine) {
  struct Case {
    std::string args, needle;
  };
  const std::vector<Case> cases = {
      {"/nonexistent/ckpt --image front=" + kImage + " --state 1,2,3,4,5,6 --instruction x", "/nonexistent/ckpt"},
      {kDemo + " --image wrist=" + kImage + " --state 1,2,3,4,5,6 --instruction x", "wrist"},
      {kDemo + " --image front=" + kImage + " --state 1,2,3 --instruction x", "expects 6"},
      {kDemo + " --image front=" + kImage + " --state 1,a,3,4,5,6 --instruction x", "'a' is not a number"},
      {kDemo + " --image front=/nonexistent.png --state 1,2,3,4,5,6 --instruction x", "/nonexistent.png"},
      {kDemo + " --image front" + " --state 1,2,3,4,5,6 --instruction x", "CAMERA=FILE"},
      {kDemo + " --image front=" + std::string(TETHER_SOURCE_DIR) + "/README.md --state 1,2,3,4,5,6 --instruction x",
       "README.md"},
      {kDemo + " --state 1,2,3,4,5,6 --instruction x", "--image"},
  };
  for (const auto& c : cases) {
    const CliRun r = run_tether("predict " + c.args);
    EXPECT_EQ(r.code, 2) << c.args << "\n" << r.err;
    EXPECT_NE(r.err.find(c.needle), std::string::npos) << c.args << "\n" << r.err;
    EXPECT_EQ(lines(r.err), 1) << c.args << "\n" << r.err;
    EXPECT_TRUE(r.out.empty()) << c.args;
  }
}

TEST(PredictCli, CorruptWeightsNameTheFile) {
  const fs::path dir = tether::testing::scratch_dir() / "corrupt";
  fs::remove_all(dir);
  fs::copy(kDemo, dir, fs::copy_options::recursive);
  fs::resize_file(dir / "model.safetensors", fs::file_size(dir / "model.safetensors") / 2);
  const CliRun r = run_tether("predict " + dir.string() + " --image front=" + kImage + " --state 1,2,3,4,5,6 --instruction x");
  EXPECT_EQ(r.code, 2) << r.err;
  EXPECT_NE(r.err.find("model.safetensors"), std::string::npos) << r.err;
  fs::remove_all(dir);
}

TEST(PredictCli, MissingStatsAreAnnounced) {
  const std::string ckpt = std::string(TETHER_FIXTURES_DIR) + "/smolvla/cam1_nostats/checkpoint";
  const std::string img = std::string(TETHER_FIXTURES_DIR) + "/smolvla/cam1_nostats/inputs/camera1_0.png";
  const CliRun r = run_tether("predict " + ckpt + " --image camera1=" + img + " --state 0,0,0,0,0,0 --instruction 'go' --json");
  ASSERT_EQ(r.code, 0) << r.err;
  EXPECT_NE(r.err.find("warning: observation.state"), std::string::npos) << r.err;
  EXPECT_NE(r.err.find("no stats"), std::string::npos) << r.err;
}
