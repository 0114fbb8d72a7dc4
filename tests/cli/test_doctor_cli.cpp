// `tether doctor`: machine checks, model directory checks, JSON output and exit codes.
#include <gtest/gtest.h>

#include <filesystem>
#include <set>

#include "cli_runner.h"
#include "core/json_util.h"
#include "scratch_dir.h"

using namespace tether;
namespace fs = std::filesystem;

TEST(DoctorCli, ReportsMachineAndModel) {
  const CliRun r = run_tether("doctor " + std::string(TETHER_SOURCE_DIR) + "/models/demo/smolvla-demo --json");
  ASSERT_EQ(r.code, 0) << r.out << r.err;
  const Json j = Json::parse(r.out);
  EXPECT_TRUE(j["ok"].get<bool>());
  std::set<std::string> groups;
  for (const auto& c : j["checks"]) groups.insert(c["group"].get<std::string>());
  for (const char* g : {"cpu", "memory", "disk", "cuda", "model"}) EXPECT_TRUE(groups.count(g)) << g;
  bool hashed = false;
  for (const auto& c : j["checks"])
    hashed |= c["check"] == "sha256" && c["detail"].get<std::string>().size() == std::string("model.safetensors ").size() + 64;
  EXPECT_TRUE(hashed) << r.out;
  const CliRun table = run_tether("doctor");
  EXPECT_EQ(table.code, 0);
  EXPECT_NE(table.out.find("GEMM library"), std::string::npos);
}

TEST(DoctorCli, BrokenModelFailsWithRemedy) {
  const fs::path dir = tether::testing::scratch_dir() / "doctor";
  fs::create_directories(dir);
  const CliRun r = run_tether("doctor " + dir.string());
  EXPECT_EQ(r.code, 1) << r.out;
  EXPECT_NE(r.out.find("model.safetensors missing"), std::string::npos) << r.out;
  EXPECT_NE(r.out.find("->"), std::string::npos) << r.out;
  fs::remove_all(dir);
}
