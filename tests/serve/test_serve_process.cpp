// The real `tether serve` process on the demo checkpoint: port line, health turning 200, a 50x6 chunk from /act,
// batched results equal to single-request results, and exit 0 on SIGTERM.
#include <gtest/gtest.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <regex>
#include <thread>

#include "core/json_util.h"
#include "http_test_client.h"
#include "serve_process.h"
#include "serve/base64.h"
#include "scratch_dir.h"

using namespace tether;
using namespace tether::serve::testing;

namespace {

const std::string kDemo = std::string(TETHER_SOURCE_DIR) + "/models/demo/smolvla-demo";
const std::string kImage = std::string(TETHER_SOURCE_DIR) + "/models/demo/sample.png";
// A dispatch cap without bf16 instructions on this architecture.
#if defined(__x86_64__)
const std::string kNoBf16Cap = "TETHER_MAX_CPU_ISA=AVX2";
#else
const std::string kNoBf16Cap = "TETHER_MAX_CPU_ISA=NEON";
#endif

std::string act_body(uint64_t seed) {
  std::ifstream in(kImage, std::ios::binary);
  const std::string png((std::istreambuf_iterator<char>(in)), {});
  const Json body = {{"instruction", "pick up the cube"},
                     {"state", {0, 90, 90, 45, 0, 20}},
                     {"images", {{"front", serve::base64_encode(reinterpret_cast<const uint8_t*>(png.data()), png.size())}}},
                     {"seed", seed}};
  return body.dump();
}

std::vector<float> flat_actions(const Json& reply) {
  std::vector<float> out;
  for (const auto& row : reply.at("actions"))
    for (const auto& v : row) out.push_back(v.get<float>());
  return out;
}

}  // namespace

TEST(ServeProcess, ServesTheDemoCheckpointAndBatchesWithoutChangingResults) {
  ServeProcess server({"serve", kDemo, "--port", "0", "--max-batch", "4", "--batch-timeout-ms", "300"});
  const uint16_t port = server.port();
  wait_ready(port);

  const HttpReply first = http_post(port, "/act", act_body(1));
  ASSERT_EQ(first.status, 200) << first.body;
  const Json j = Json::parse(first.body);
  EXPECT_EQ(j["num_actions"], 50);
  EXPECT_EQ(j["action_dim"], 6);
  ASSERT_EQ(j["actions"].size(), 50u);
  for (const auto& row : j["actions"]) ASSERT_EQ(row.size(), 6u);
  EXPECT_EQ(first.headers.at("x-tether-request-id"), j["request_id"].get<std::string>());

  // Four concurrent requests with different seeds share one forward pass (the 300 ms window gathers them)...
  constexpr int n = 4;
  std::vector<HttpReply> batched(n);
  std::vector<std::thread> clients;
  for (int i = 0; i < n; ++i)
    clients.emplace_back([&, i] { batched[i] = http_post(port, "/act", act_body(100 + i)); });
  for (auto& c : clients) c.join();
  // ...and each alone gives the same actions.
  float max_diff = 0;
  int max_batch_seen = 0;
  for (int i = 0; i < n; ++i) {
    ASSERT_EQ(batched[i].status, 200) << batched[i].body;
    const Json b = Json::parse(batched[i].body);
    max_batch_seen = std::max(max_batch_seen, b["batch_size"].get<int>());
    const HttpReply alone = http_post(port, "/act", act_body(100 + i));
    ASSERT_EQ(alone.status, 200) << alone.body;
    const Json a = Json::parse(alone.body);
    EXPECT_EQ(a["batch_size"], 1);
    const auto va = flat_actions(a), vb = flat_actions(b);
    ASSERT_EQ(va.size(), vb.size());
    for (std::size_t k = 0; k < va.size(); ++k) max_diff = std::max(max_diff, std::fabs(va[k] - vb[k]));
  }
  std::printf("batched (batch_size up to %d) vs single-request actions: max |diff| = %g\n", max_batch_seen, max_diff);
  EXPECT_GT(max_batch_seen, 1) << "concurrent requests never shared a forward pass";
  EXPECT_LE(max_diff, 1e-5f);

  // Different seeds really do give different chunks (the comparison above is not vacuous).
  EXPECT_NE(flat_actions(Json::parse(batched[0].body)), flat_actions(Json::parse(batched[1].body)));

  EXPECT_EQ(server.terminate(), 0);
}

namespace {

struct CliRun {
  int code = -1;
  std::string out;  // stdout and stderr together
};

CliRun run_tether(const std::string& args, const std::string& env = "") {
  CliRun r;
  FILE* pipe = popen((env + (env.empty() ? "" : " ") + std::string(TETHER_BINARY) + " " + args + " 2>&1").c_str(), "r");
  char buf[4096];
  std::size_t n;
  while ((n = fread(buf, 1, sizeof buf, pipe)) > 0) r.out.append(buf, n);
  const int status = pclose(pipe);
  r.code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  return r;
}

std::filesystem::path temp_dir(const std::string& name) {
  const auto dir = tether::testing::scratch_dir() / "go" / name;
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  return dir;
}

}  // namespace

TEST(GoCli, ListsTheRegistry) {
  const CliRun r = run_tether("go --list");
  ASSERT_EQ(r.code, 0) << r.out;
  for (const char* id : {"smolvla-demo", "smolvla-base", "pi0-base", "pi05-base", "gr00t-n1.6"})
    EXPECT_NE(r.out.find(id), std::string::npos) << id << "\n" << r.out;
  EXPECT_NE(r.out.find("lerobot/smolvla_base"), std::string::npos);
  EXPECT_NE(r.out.find("nvidia/GR00T-N1.6-3B"), std::string::npos);
}

TEST(GoCli, UnknownIdAndUnsupportedFamilyExit2) {
  CliRun r = run_tether("go --model no-such-model");
  EXPECT_EQ(r.code, 2) << r.out;
  EXPECT_NE(r.out.find("smolvla-demo"), std::string::npos) << "should list the known ids: " << r.out;
  // An entry the build does not support yet (every shipped one is supported): a registry of one.
  const auto dir = temp_dir("registry");
  std::ofstream(dir / "registry.json") << R"({"schema_version": 1, "models": {"future-vla": {"family": "future",
      "hf_repo": "example/future-vla", "description": "a family this build does not know", "license": "apache-2.0",
      "supported": false, "parameters": 1000, "figures": []}}})";
  r = run_tether("go --model future-vla", "TETHER_REGISTRY=" + (dir / "registry.json").string());
  EXPECT_EQ(r.code, 2) << r.out;
  EXPECT_NE(r.out.find("not supported"), std::string::npos) << r.out;
  EXPECT_EQ(run_tether("go").code, 2);
}

TEST(GoCli, MissingDownloadSaysHowToGetIt) {
  const auto cache = temp_dir("empty_cache");
  // Offline: the pull go attempts must fail at once, without reaching for the network.
  const std::string env = "HF_HUB_CACHE=" + cache.string() + " HF_HUB_OFFLINE=1 ";
  const CliRun m = [&] {
    CliRun out;
    FILE* pipe = popen((env + TETHER_BINARY + " go --model smolvla-base --port 0 2>&1").c_str(), "r");
    char buf[4096];
    std::size_t n;
    while ((n = fread(buf, 1, sizeof buf, pipe)) > 0) out.out.append(buf, n);
    const int status = pclose(pipe);
    out.code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
    return out;
  }();
  EXPECT_EQ(m.code, 2) << m.out;
  EXPECT_NE(m.out.find("lerobot/smolvla_base"), std::string::npos) << m.out;
  EXPECT_NE(m.out.find("download"), std::string::npos) << m.out;
  EXPECT_EQ(m.out.find("listening"), std::string::npos) << m.out;
}

TEST(GoCli, ServesTheBundledDemo) {
  // go exports the model into the Tether cache (keyed by version and precision), verifies it, then serves it.
  // Capped at AVX2 (NEON on aarch64) so go picks fp32 on every CPU (with native bf16 it would pick bf16).
  const auto tether_cache = temp_dir("tether_cache");
  const auto export_dir = tether_cache / "exports" / TETHER_VERSION_STR / "smolvla-demo-fp32";
  {
    ServeProcess server({"go", "--model", "smolvla-demo", "--port", "0"},
                        {"TETHER_CACHE=" + tether_cache.string(), kNoBf16Cap});
    wait_ready(server.port());
    const HttpReply r = http_post(server.port(), "/act", act_body(5));
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_EQ(Json::parse(r.body)["actions"].size(), 50u);
    EXPECT_EQ(server.terminate(), 0);
  }
  ASSERT_TRUE(std::filesystem::exists(export_dir / "VERIFICATION.md"));
  const auto first = std::filesystem::last_write_time(export_dir / "model.safetensors");
  {  // A second start reuses the export; a stale one (another Tether version) would be rebuilt.
    ServeProcess again({"go", "--model", "smolvla-demo", "--port", "0"},
                       {"TETHER_CACHE=" + tether_cache.string(), kNoBf16Cap});
    wait_ready(again.port());
    EXPECT_EQ(again.terminate(), 0);
  }
  EXPECT_EQ(std::filesystem::last_write_time(export_dir / "model.safetensors"), first);
}

TEST(GoCli, FindsACheckpointInTheHuggingFaceCache) {
  // The hub cache layout: models--org--name/refs/main names the snapshot directory holding the files.
  const auto cache = temp_dir("hf_home") / "hub";
  const auto repo = cache / "models--lerobot--smolvla_base";
  std::filesystem::create_directories(repo / "refs");
  const std::string commit = "0123abcd0123abcd0123abcd0123abcd0123abcd";  // a real cache names 40-hex commits
  std::ofstream(repo / "refs" / "main") << commit << "\n";
  std::filesystem::create_directories(repo / "snapshots");
  std::filesystem::create_directory_symlink(kDemo, repo / "snapshots" / commit);
  // A registry given by TETHER_REGISTRY, and HF_HOME (not HF_HUB_CACHE) locating the cache.
  const auto reg = temp_dir("registry") / "registry.json";
  std::ofstream(reg) << R"({"models": {"base": {"family": "smolvla", "hf_repo": "lerobot/smolvla_base", "supported": true}}})";
  ServeProcess server({"go", "--model", "base", "--port", "0"},
                      {"TETHER_REGISTRY=" + reg.string(), "HF_HOME=" + cache.parent_path().string(), "HF_HUB_CACHE=",
                       "TETHER_CACHE=" + temp_dir("go_cache").string()});
  wait_ready(server.port());
  const Json health = Json::parse(http_get(server.port(), "/health").body);
  EXPECT_EQ(health["state"], "ready");
  EXPECT_EQ(server.terminate(), 0);
}
