// --backend on the verbs that load a model: cpu and auto run; cuda runs where a GPU is usable and, elsewhere, fails
// before the model loads with one line and exit code 2; doctor says whether this build and machine have the backend.
#include <gtest/gtest.h>

#include <algorithm>

#include "backend/backend.h"
#include "cli_runner.h"
#include "core/json_util.h"

using namespace tether;

namespace {

const std::string kDemo = std::string(TETHER_SOURCE_DIR) + "/models/demo/smolvla-demo";
const std::string kImage = std::string(TETHER_SOURCE_DIR) + "/models/demo/sample.png";
const std::string kGood = kDemo + " --image front=" + kImage + " --state 0,90,90,45,0,20 --instruction 'pick up the cube'";

bool cuda_here() { return backend::backend_usable("cuda"); }

int lines(const std::string& s) { return int(std::count(s.begin(), s.end(), '\n')); }

}  // namespace

TEST(BackendCli, CpuAndAutoRunAndSayWhichBackendRan) {
  const CliRun cpu = run_tether("predict " + kGood + " --seed 5 --json --backend cpu");
  ASSERT_EQ(cpu.code, 0) << cpu.err;
  EXPECT_EQ(Json::parse(cpu.out)["inference_mode"], "cpu-fp32");
  const CliRun automatic = run_tether("predict " + kGood + " --seed 5 --json --backend auto");
  ASSERT_EQ(automatic.code, 0) << automatic.err;
  const Json a = Json::parse(automatic.out);
  EXPECT_EQ(a["inference_mode"], cuda_here() ? "cuda-fp32" : "cpu-fp32");
  if (!cuda_here()) {
    EXPECT_EQ(a["actions"], Json::parse(cpu.out)["actions"]) << "auto fell back to the same CPU backend";
  }
}

TEST(BackendCli, CudaWithoutAUsableGpuIsOneLineAndExitTwo) {
  std::string why;
  if (backend::backend_usable("cuda", &why)) GTEST_SKIP() << "skipped: a CUDA device is usable here";
  for (const std::string& verb : {"predict " + kGood, "bench " + kGood + " --iterations 1 --warmup 0",
                                 "serve " + kDemo + " --port 0", "export " + kDemo + " -o /nonexistent/never-written"}) {
    const CliRun r = run_tether(verb + " --backend cuda");
    EXPECT_EQ(r.code, 2) << verb << "\n" << r.err;
    EXPECT_EQ(lines(r.err), 1) << verb << "\n" << r.err;
    EXPECT_NE(r.err.find("cuda"), std::string::npos) << r.err;
    EXPECT_NE(r.err.find(why), std::string::npos) << "the reason backend_usable gives: " << why << "\n" << r.err;
  }
}

TEST(BackendCli, UnknownBackendIsAUsageError) {
  const CliRun r = run_tether("predict " + kGood + " --backend tpu");
  EXPECT_EQ(r.code, 2);
  EXPECT_NE(r.err.find("--backend"), std::string::npos) << r.err;
}

TEST(BackendCli, DoctorReportsTheCudaBackend) {
  const CliRun r = run_tether("doctor --json");
  ASSERT_EQ(r.code, 0) << r.err;
  const Json j = Json::parse(r.out);
  bool found = false;
  for (const auto& c : j["checks"]) {
    if (c["group"] != "cuda" || c["check"] != "backend") continue;
    found = true;
    const auto compiled = backend::compiled_backends();
    const bool built = std::find(compiled.begin(), compiled.end(), "cuda") != compiled.end();
    std::string why;
    const bool usable = backend::backend_usable("cuda", &why);
    EXPECT_EQ(c["detail"].get<std::string>(), usable ? std::string("compiled in and usable: --backend cuda (or auto) runs models on the GPU") : why);
    const std::string status = c["status"].get<std::string>();
    if (usable) {
      EXPECT_EQ(status, "ok");
    } else if (!built) {
      EXPECT_EQ(status, "skip");
    } else {
      EXPECT_TRUE(status == "warn" || status == "skip") << c.dump();
    }
  }
  EXPECT_TRUE(found) << r.out;
}
