// The real `tether serve` process on the demo checkpoint: port line, health turning 200, a 50x6 chunk from /act,
// batched results equal to single-request results, and exit 0 on SIGTERM.
#include <gtest/gtest.h>
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <fstream>
#include <regex>
#include <thread>

#include "core/json_util.h"
#include "http_test_client.h"
#include "serve/base64.h"

extern char** environ;

using namespace tether;
using namespace tether::serve::testing;

namespace {

const std::string kDemo = std::string(TETHER_SOURCE_DIR) + "/models/demo/smolvla-demo";
const std::string kImage = std::string(TETHER_SOURCE_DIR) + "/models/demo/sample.png";

// A `tether serve` child whose stdout is read for the listening line. SIGKILLed if a test leaves it running.
class ServeProcess {
 public:
  explicit ServeProcess(std::vector<std::string> extra) {
    int out[2];
    if (pipe(out) != 0) throw std::runtime_error("pipe failed");
    std::vector<std::string> args = {TETHER_BINARY, "serve", kDemo, "--port", "0"};
    args.insert(args.end(), extra.begin(), extra.end());
    std::vector<char*> argv;
    for (auto& a : args) argv.push_back(a.data());
    argv.push_back(nullptr);
    posix_spawn_file_actions_t fa;
    posix_spawn_file_actions_init(&fa);
    posix_spawn_file_actions_adddup2(&fa, out[1], STDOUT_FILENO);
    posix_spawn_file_actions_addclose(&fa, out[0]);
    if (posix_spawn(&pid_, argv[0], &fa, nullptr, argv.data(), environ) != 0) throw std::runtime_error("spawn failed");
    posix_spawn_file_actions_destroy(&fa);
    close(out[1]);
    out_ = fdopen(out[0], "r");
    char line[512];
    if (!fgets(line, sizeof line, out_)) throw std::runtime_error("tether serve printed no listening line");
    std::smatch m;
    const std::string s(line);
    if (!std::regex_search(s, m, std::regex(R"(^tether serve: listening on http://127\.0\.0\.1:(\d+)\n$)")))
      throw std::runtime_error("unexpected first line: " + s);
    port_ = uint16_t(std::stoi(m[1]));
  }
  ~ServeProcess() {
    if (pid_ > 0) {
      kill(pid_, SIGKILL);
      waitpid(pid_, nullptr, 0);
    }
    if (out_) fclose(out_);
  }
  uint16_t port() const { return port_; }
  // SIGTERM, then the exit status (or -1 if it did not exit normally within 30 s).
  int terminate() {
    kill(pid_, SIGTERM);
    for (int i = 0; i < 3000; ++i) {
      int status = 0;
      if (waitpid(pid_, &status, WNOHANG) == pid_) {
        pid_ = -1;
        return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(10));
    }
    return -1;
  }

 private:
  pid_t pid_ = -1;
  FILE* out_ = nullptr;
  uint16_t port_ = 0;
};

void wait_ready(uint16_t port) {
  for (int i = 0; i < 600; ++i) {
    if (http_get(port, "/health").status == 200) return;
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  FAIL() << "/health never turned 200";
}

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
  ServeProcess server({"--max-batch", "4", "--batch-timeout-ms", "300"});
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
