// `tether serve` and `tether go` on pi0 and pi0.5 checkpoints (the oracle fixtures), spoken to over HTTP: batching
// prompts of different lengths, /config, a missing camera, bad requests, an export served with an empty hub cache,
// `go` pulling from a local fake hub, and each safety wedge acting on a pi0 model.
#include <gtest/gtest.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <optional>
#include <set>
#include <thread>

#include "core/json_util.h"
#include "http_test_client.h"
#include "serve/base64.h"
#include "serve_process.h"
#include "scratch_dir.h"

using namespace tether;
using namespace tether::serve::testing;
namespace fs = std::filesystem;

namespace {

const fs::path kFixtures = TETHER_FIXTURES_DIR;
const fs::path kHub = kFixtures / "paligemma_hub";
const std::string kHubEnv = "HF_HUB_CACHE=" + kHub.string();
const std::string kTokenizerRepo = "google/paligemma-3b-pt-224";

std::string read(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  return {std::istreambuf_iterator<char>(in), {}};
}

std::string image_b64(const fs::path& p) {
  const std::string bytes = read(p);
  return serve::base64_encode(reinterpret_cast<const uint8_t*>(bytes.data()), bytes.size());
}

// A fixture case: its checkpoint and a request body that fits it.
struct Case {
  std::string family, name;
  std::vector<std::pair<std::string, std::string>> images;  // camera -> file under inputs/
  std::vector<float> state;
  fs::path checkpoint() const { return kFixtures / family / name / "checkpoint"; }
  Json body(const std::string& instruction, uint64_t seed) const {
    Json images_json = Json::object();
    for (const auto& [camera, file] : images) images_json[camera] = image_b64(kFixtures / family / name / "inputs" / file);
    return {{"instruction", instruction}, {"state", state}, {"images", images_json}, {"seed", seed}};
  }
};
const Case kPi0{"pi0", "cam1_stats", {{"camera1", "camera1_0.png"}}, {0.5f, -1, 2, 0, 1, 3}};
const Case kPi05{"pi05", "cam1_quantiles_bins", {{"camera1", "camera1_0.png"}}, {0.1f, 0.2f, 0.3f, 0.4f, 0.5f, 0.6f, 0.7f, 0.8f}};
const Case kPi0Missing{"pi0", "cam3_missing_empty", {{"camera1", "camera1_0.png"}, {"camera3", "camera3_0.png"}}, {0, 0, 0, 0, 0, 0, 0}};
const Case kPi0NoStats{"pi0", "cam3_nostats_trunc", {{"camera1", "camera1_0.png"}}, {0, 0, 0, 0, 0, 0, 0}};

std::vector<float> flat_actions(const Json& reply) {
  std::vector<float> out;
  for (const auto& row : reply.at("actions"))
    for (const auto& v : row) out.push_back(v.get<float>());
  return out;
}

HttpReply act(uint16_t port, const Json& body) { return http_post(port, "/act", body.dump()); }

Json act_ok(uint16_t port, const Json& body) {
  const HttpReply r = act(port, body);
  EXPECT_EQ(r.status, 200) << r.body;
  return r.status == 200 ? Json::parse(r.body) : Json::object();
}

std::string error_code(const HttpReply& r) {
  try {
    return Json::parse(r.body).at("error").at("code").get<std::string>();
  } catch (const std::exception&) {
    return "(no error code in: " + r.body + ")";
  }
}

// A scratch directory per test, removed afterwards.
struct Scratch {
  fs::path path;
  explicit Scratch(const std::string& name)
      : path(tether::testing::scratch_dir() / ("pi0_serve_" + name)) {
    fs::remove_all(path);
    fs::create_directories(path);
  }
  ~Scratch() { fs::remove_all(path); }
  fs::path operator/(const std::string& p) const { return path / p; }
};

// A process expected to exit on its own (a server refusing to start, a `tether traces` query).
struct Exit {
  int code = -1;
  std::string out, err;
};
Exit run_to_exit(const std::string& prefix, const std::string& args) {
  const fs::path err_file = tether::testing::scratch_dir() / "pi0_serve_err";
  Exit r;
  FILE* pipe = popen((prefix + " timeout 120 " + TETHER_BINARY + " " + args + " 2>" + err_file.string()).c_str(), "r");
  char buf[4096];
  std::size_t n;
  while ((n = fread(buf, 1, sizeof buf, pipe)) > 0) r.out.append(buf, n);
  const int status = pclose(pipe);
  r.code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  r.err = read(err_file);
  fs::remove(err_file);
  return r;
}

void edit_config(const fs::path& dir, const std::function<void(Json&)>& edit) {
  Json c = read_json_file((dir / "config.json").string());
  edit(c);
  std::ofstream(dir / "config.json", std::ios::trunc) << c.dump(4);
}

// An embodiment file: `n` joints with the action range [-range, range], position limits far outside it unless
// `max_position` is given, and an optional velocity limit.
fs::path write_embodiment(const fs::path& path, int n, double range, std::optional<double> max_position = {},
                          std::optional<double> max_velocity = {}) {
  Json joints = Json::array();
  for (int j = 0; j < n; ++j) {
    const std::string name = std::string("j") += std::to_string(j);  // (GCC 12 warns on "j" + std::to_string(j))
    Json joint = {{"name", name}, {"min", -range}, {"max", range},
                  {"min_position", -max_position.value_or(1e9)}, {"max_position", max_position.value_or(1e9)}};
    if (max_velocity) joint["max_velocity"] = *max_velocity;
    joints.push_back(joint);
  }
  std::ofstream(path) << Json{{"name", "test_arm"}, {"units", "test units"}, {"control_rate_hz", 10}, {"joints", joints}}.dump(2);
  return path;
}

std::vector<std::string> serve_args(const Case& c, const std::vector<std::string>& extra = {}) {
  std::vector<std::string> args = {"serve", c.checkpoint().string(), "--port", "0"};
  args.insert(args.end(), extra.begin(), extra.end());
  return args;
}

}  // namespace

TEST(Pi0Serve, BatchedPromptsOfDifferentLengthsGetTheActionsTheyGetAlone) {
  // Instructions of very different token counts (the last one past tokenizer_max_length, cut as upstream does) and,
  // for pi0.5, states written into the prompt: the batch pads every prefix to the longest, masked.
  const std::vector<std::string> instructions = {
      "go", "pick up the red cube and put it in the bowl",
      "open the top drawer of the cabinet, take out the blue block, place it on the plate next to the cup, then close "
      "the drawer again and return the arm to its home position without touching anything else on the table"};
  for (const Case& c : {kPi0, kPi05}) {
    ServeProcess server(serve_args(c, {"--max-batch", "4", "--batch-timeout-ms", "400"}), {kHubEnv});
    wait_ready(server.port());
    const int n = int(instructions.size());
    std::vector<Json> bodies;
    for (int i = 0; i < n; ++i) {
      Json b = c.body(instructions[i], 20 + i);
      for (auto& v : b["state"]) v = v.get<float>() * float(i + 1) * 0.3f;  // pi0.5: other state bins, other lengths
      bodies.push_back(b);
    }
    std::vector<HttpReply> batched(n);
    std::vector<std::thread> clients;
    for (int i = 0; i < n; ++i) clients.emplace_back([&, i] { batched[i] = act(server.port(), bodies[i]); });
    for (auto& t : clients) t.join();
    int max_batch = 0;
    float max_diff = 0;
    for (int i = 0; i < n; ++i) {
      ASSERT_EQ(batched[i].status, 200) << batched[i].body;
      const Json b = Json::parse(batched[i].body);
      max_batch = std::max(max_batch, b["batch_size"].get<int>());
      const Json alone = act_ok(server.port(), bodies[i]);
      EXPECT_EQ(alone["batch_size"], 1);
      const auto va = flat_actions(alone), vb = flat_actions(b);
      ASSERT_EQ(va.size(), 8u * 6u);
      ASSERT_EQ(va.size(), vb.size());
      for (std::size_t k = 0; k < va.size(); ++k) max_diff = std::max(max_diff, std::fabs(va[k] - vb[k]));
    }
    std::printf("%s: batched (up to %d) vs alone, prompts of different lengths: max |diff| = %g\n", c.family.c_str(),
                max_batch, max_diff);
    EXPECT_GT(max_batch, 1) << c.family << ": the concurrent requests never shared a forward pass";
    EXPECT_LE(max_diff, 1e-5f) << c.family;
    // The instruction reaches the model: two prompts, two chunks.
    EXPECT_NE(flat_actions(Json::parse(batched[0].body)), flat_actions(Json::parse(batched[1].body)));
    EXPECT_EQ(server.terminate(), 0);
  }
}

TEST(Pi0Serve, ConfigReportsTheFamilyAndAMissingCameraIsAWarning) {
  for (const std::string family : {"pi0", "pi05"}) {
    Case c = kPi0Missing;
    c.family = family;
    ServeProcess server(serve_args(c), {kHubEnv});
    wait_ready(server.port());
    const HttpReply config = http_get(server.port(), "/config");
    ASSERT_EQ(config.status, 200) << config.body;
    const Json j = Json::parse(config.body);
    EXPECT_EQ(j["family"], family);
    EXPECT_EQ(j["stages"], Json::array({"preprocess", "vision", "prefix", "denoise"}));
    EXPECT_EQ(j["missing_camera_rule"],
              "an absent camera is replaced by a -1 image that is masked out (as upstream); at least one camera must be "
              "present");
    EXPECT_EQ(j["cameras"].size(), 4u);
    EXPECT_EQ(j["chunk_size"], 8);
    EXPECT_EQ(j["action_dim"], 7);

    // camera2 left out: answered, with a warning; the config's empty camera is the model's own, never a warning.
    const Json two = act_ok(server.port(), c.body("pick up the cube", 1));
    ASSERT_EQ(two["warnings"].size(), 1u) << two;
    EXPECT_EQ(two["warnings"][0], "no image for camera 'observation.images.camera2': masked out, as upstream does");
    EXPECT_EQ(two["actions"].size(), 8u);
    Case one = c;
    one.images = {{"camera3", "camera3_0.png"}};
    const Json only3 = act_ok(server.port(), one.body("pick up the cube", 1));
    EXPECT_EQ(only3["warnings"].size(), 2u) << only3;
    EXPECT_NE(flat_actions(only3), flat_actions(two));
    EXPECT_EQ(server.terminate(), 0);
  }
}

TEST(Pi0Serve, BadRequestsAreHttpErrorsAndTheServerKeepsServing) {
  for (const Case& c : {kPi0, kPi05}) {
    ServeProcess server(serve_args(c, {"--max-batch", "4", "--batch-timeout-ms", "200"}), {kHubEnv});
    wait_ready(server.port());
    const uint16_t port = server.port();
    Json short_state = c.body("go", 1);
    short_state["state"] = {1, 2, 3};
    Json no_images = c.body("go", 1);
    no_images["images"] = Json::object();
    Json unknown = c.body("go", 1);
    unknown["images"]["wrist"] = unknown["images"]["camera1"];
    Json not_an_image = c.body("go", 1);
    not_an_image["images"]["camera1"] = image_b64(fs::path(TETHER_SOURCE_DIR) / "README.md");
    // JSON cannot carry invalid UTF-8: raw bytes or a lone surrogate escape are not JSON.
    const std::string raw = c.body("XX", 1).dump();
    const std::size_t at = raw.find("XX");
    const std::string bad_bytes = raw.substr(0, at) + "\xff\xfe" + raw.substr(at + 2);
    const std::string lone_surrogate = raw.substr(0, at) + "\\udcff" + raw.substr(at + 2);
    struct Bad {
      std::string body;
      int status;
      std::string code, needle;
    };
    const std::vector<Bad> cases = {
        {short_state.dump(), 400, "invalid_state", "state has 3 values, the model expects " + std::to_string(c.state.size())},
        {no_images.dump(), 400, "missing_field", "at least one camera image"},
        {unknown.dump(), 400, "unknown_camera", "wrist"},
        {not_an_image.dump(), 400, "invalid_image", "camera1"},
        {bad_bytes, 400, "bad_json", "UTF-8"},
        {lone_surrogate, 400, "bad_json", "surrogate"},
    };
    // Sent together with a good request: a bad one is refused before it can join (and fail) a batch.
    std::vector<HttpReply> replies(cases.size());
    HttpReply good;
    std::vector<std::thread> clients;
    clients.emplace_back([&] { good = act(port, c.body("pick up the cube", 7)); });
    for (std::size_t i = 0; i < cases.size(); ++i)
      clients.emplace_back([&, i] { replies[i] = http_post(port, "/act", cases[i].body); });
    for (auto& t : clients) t.join();
    for (std::size_t i = 0; i < cases.size(); ++i) {
      EXPECT_EQ(replies[i].status, cases[i].status) << c.family << " " << i << ": " << replies[i].body;
      EXPECT_EQ(error_code(replies[i]), cases[i].code) << replies[i].body;
      EXPECT_NE(replies[i].body.find(cases[i].needle), std::string::npos) << replies[i].body;
    }
    ASSERT_EQ(good.status, 200) << good.body;
    EXPECT_EQ(flat_actions(Json::parse(good.body)), flat_actions(act_ok(port, c.body("pick up the cube", 7))));
    EXPECT_EQ(http_get(port, "/health").status, 200);
    EXPECT_EQ(server.terminate(), 0);
  }
}

TEST(Pi0Serve, AnExportServesWithAnEmptyHubCache) {
  Scratch tmp("export");
  fs::create_directories(tmp / "empty_hub");
  for (const Case& c : {kPi0, kPi05}) {
    const fs::path out = tmp / c.family;
    const Exit e = run_to_exit(kHubEnv, "export " + c.checkpoint().string() + " -o " + out.string() + " --precision bf16");
    ASSERT_EQ(e.code, 0) << e.err;
    ServeProcess server({"serve", out.string(), "--port", "0"}, {"HF_HUB_CACHE=" + (tmp / "empty_hub").string()});
    wait_ready(server.port());
    const Json config = Json::parse(http_get(server.port(), "/config").body);
    EXPECT_EQ(config["family"], c.family);
    EXPECT_EQ(config["weights_dtype"], "BF16");
    const Json a = act_ok(server.port(), c.body("pick up the cube", 3));
    EXPECT_EQ(a["actions"].size(), 8u);
    EXPECT_EQ(server.terminate(), 0);
  }
}

// ---- `tether go` against a local fake hub ----

namespace {

// fake_hub.py serving the given repositories (repo id -> directory); it exits when its stdin closes.
class FakeHub {
 public:
  explicit FakeHub(const std::vector<std::pair<std::string, fs::path>>& repos) {
    int in_pipe[2], out_pipe[2];
    if (::pipe(in_pipe) != 0 || ::pipe(out_pipe) != 0) throw std::runtime_error("pipe failed");
    std::vector<std::string> args = {TETHER_PYTHON3, std::string(TETHER_SOURCE_DIR) + "/tests/hub/fake_hub.py"};
    for (const auto& [id, dir] : repos) {
      args.push_back("--repo");
      args.push_back(id + "=" + dir.string());
    }
    std::vector<char*> argv;
    for (auto& a : args) argv.push_back(a.data());
    argv.push_back(nullptr);
    pid_ = ::fork();
    if (pid_ == 0) {
      ::dup2(in_pipe[0], 0);
      ::dup2(out_pipe[1], 1);
      ::close(in_pipe[1]);
      ::close(out_pipe[0]);
      ::execv(TETHER_PYTHON3, argv.data());
      ::_exit(127);
    }
    ::close(in_pipe[0]);
    ::close(out_pipe[1]);
    stdin_fd_ = in_pipe[1];
    std::string line;
    char ch;
    while (::read(out_pipe[0], &ch, 1) == 1 && ch != '\n') line += ch;
    ::close(out_pipe[0]);
    if (line.empty() || line[0] != '{') throw std::runtime_error("tests/hub/fake_hub.py did not start");
    url_ = Json::parse(line).at("hub").get<std::string>();
  }
  ~FakeHub() {
    ::close(stdin_fd_);
    ::waitpid(pid_, nullptr, 0);
  }
  const std::string& url() const { return url_; }

 private:
  pid_t pid_ = -1;
  int stdin_fd_ = -1;
  std::string url_;
};

}  // namespace

TEST(Pi0Go, PullsExportsVerifiesAndServesFromTheHub) {
  // The registry's pi0-base and pi05-base, served by a local hub: the tiny fixture checkpoints as lerobot/pi0_base and
  // lerobot/pi05_base, the stand-in tokenizer as google/paligemma-3b-pt-224 (what the entries' `requires` pull).
  const fs::path tokenizer =
      kHub / "models--google--paligemma-3b-pt-224" / "snapshots" / "7f1a0c1b5e0d4a2c9b3e8f6d5c4b3a2918070605";
  FakeHub hub({{"lerobot/pi0_base", kPi0.checkpoint()}, {"lerobot/pi05_base", kPi05.checkpoint()}, {kTokenizerRepo, tokenizer}});
  Scratch tmp("go");
  const std::string version = TETHER_VERSION_STR;
  for (const auto& [id, c] : {std::pair<std::string, const Case*>{"pi0-base", &kPi0}, {"pi05-base", &kPi05}}) {
    const fs::path log = tmp / (id + ".log");
    const std::vector<std::string> env = {"HF_ENDPOINT=" + hub.url(), "HF_HUB_CACHE=" + (tmp / "hf").string(),
                                          "HF_HOME=" + (tmp / "hf_home").string(), "HF_HUB_OFFLINE=",
                                          "TETHER_CACHE=" + (tmp / "tether").string()};
    {
      // --precision fp32: the registry's 3.3B parameters would otherwise pick bf16 on a small machine.
      ServeProcess server({"go", "--model", id, "--port", "0", "--precision", "fp32"}, env, log.string());
      wait_ready(server.port());
      const Json config = Json::parse(http_get(server.port(), "/config").body);
      EXPECT_EQ(config["family"], c->family);
      const Json a = act_ok(server.port(), c->body("pick up the cube", 4));
      EXPECT_EQ(a["actions"].size(), 8u) << a;
      EXPECT_EQ(server.terminate(), 0);
    }
    const std::string err = read(log);
    for (const std::string& line : std::vector<std::string>{"tether go: " + id + " is not on disk: pulling it",
                                   "export verified, max |diff| against the source"})
      EXPECT_NE(err.find(line), std::string::npos) << line << "\n" << err;
    // Both repos are in the hub cache, and the export carries the tokenizer.
    const fs::path repo_dir = tmp / "hf" / ("models--lerobot--" + std::string(id == "pi0-base" ? "pi0_base" : "pi05_base"));
    EXPECT_TRUE(fs::is_directory(repo_dir)) << repo_dir;
    EXPECT_TRUE(fs::is_directory(tmp / "hf" / "models--google--paligemma-3b-pt-224")) << err;
    const fs::path exported = tmp / "tether" / "exports" / version / (id + "-fp32");
    EXPECT_TRUE(fs::exists(exported / "VERIFICATION.md")) << exported;
    EXPECT_EQ(read(exported / kTokenizerRepo / "tokenizer.model"), read(tokenizer / "tokenizer.model"));
    // A second start finds everything on disk: no pull, the same export.
    {
      ServeProcess again({"go", "--model", id, "--port", "0", "--precision", "fp32"}, env, log.string());
      wait_ready(again.port());
      EXPECT_EQ(again.terminate(), 0);
    }
    const std::string second = read(log);
    EXPECT_EQ(second.find("pulling"), std::string::npos) << second;
    EXPECT_NE(second.find("tether go: using the export in " + exported.string()), std::string::npos) << second;
  }
}

// ---- The safety wedges, each shown acting on a pi0 model ----

TEST(Pi0Wedges, EmbodimentMapsNormalisedOutputAndCutsAPaddedOne) {
  Scratch tmp("embodiment");
  // No action stats: the model's output is normalised; ur5 (7 values) maps it onto its ranges, the guard after it.
  {
    ServeProcess server(serve_args(kPi0NoStats, {"--embodiment", "ur5", "--audit-log", (tmp / "a.jsonl").string()}),
                        {kHubEnv});
    wait_ready(server.port());
    const Json config = Json::parse(http_get(server.port(), "/config").body);
    EXPECT_EQ(config["wedges"]["embodiment"]["name"], "ur5");
    EXPECT_TRUE(config["wedges"]["embodiment"]["maps_normalized_output"].get<bool>());
    const Json a = act_ok(server.port(), kPi0NoStats.body("go", 1));
    EXPECT_EQ(a["joint_names"][0], "shoulder_pan_joint");
    EXPECT_EQ(a["joint_names"][6], "gripper");
    EXPECT_EQ(a["action_dim"], 7);
    for (const auto& row : a["actions"]) {
      for (int j = 0; j < 6; ++j) EXPECT_LE(std::fabs(row[j].get<double>()), 6.283185 + 1e-5) << row;
      EXPECT_GE(row[6].get<double>(), 0.0);
      EXPECT_LE(row[6].get<double>(), 1.0);
    }
    EXPECT_EQ(server.terminate(), 0);
  }
  // A base checkpoint's action is the padded vector (action_dim = max_action_dim = 32): the embodiment keeps its
  // first joints. Against the same checkpoint served without one, column for column.
  const fs::path padded = tmp / "padded";
  fs::copy(kPi0NoStats.checkpoint(), padded, fs::copy_options::recursive);
  edit_config(padded, [](Json& c) { c["output_features"]["action"]["shape"] = {32}; });
  Case pc = kPi0NoStats;
  std::vector<float> full;
  {
    ServeProcess server({"serve", padded.string(), "--port", "0"}, {kHubEnv});
    wait_ready(server.port());
    const Json a = act_ok(server.port(), pc.body("go", 9));
    EXPECT_EQ(a["action_dim"], 32);
    full = flat_actions(a);
    EXPECT_EQ(server.terminate(), 0);
  }
  ASSERT_EQ(full.size(), 8u * 32u);
  const double range = 1000;  // maps x in [-1, 1] to 1000 x; no limit comes near
  const fs::path arm = write_embodiment(tmp / "arm6.json", 6, range);
  {
    ServeProcess server({"serve", padded.string(), "--port", "0", "--custom-embodiment-config", arm.string(),
                         "--audit-log", (tmp / "b.jsonl").string()},
                        {kHubEnv});
    wait_ready(server.port());
    const Json config = Json::parse(http_get(server.port(), "/config").body);
    EXPECT_EQ(config["wedges"]["embodiment"]["model_action_dim"], 32);
    EXPECT_EQ(config["action_dim"], 6);  // what /act answers
    const Json a = act_ok(server.port(), pc.body("go", 9));
    EXPECT_EQ(a["action_dim"], 6);
    ASSERT_EQ(a["actions"].size(), 8u);
    EXPECT_EQ(a["joint_names"].size(), 6u);
    EXPECT_FALSE(a["guard_clamped"].get<bool>()) << a["guard_violations"];
    for (std::size_t r = 0; r < 8; ++r)
      for (std::size_t j = 0; j < 6; ++j)
        EXPECT_NEAR(a["actions"][r][j].get<double>(), range * full[r * 32 + j], 1e-5 * range) << r << "," << j;
    EXPECT_EQ(server.terminate(), 0);
  }
  // What does not fit is refused at start-up, naming both counts.
  const Exit franka = run_to_exit(kHubEnv, "serve " + kPi0.checkpoint().string() + " --port 0 --embodiment franka");
  EXPECT_EQ(franka.code, 2) << franka.err;
  EXPECT_NE(franka.err.find("embodiment 'franka' has 8 joints, the model outputs 6 action values"), std::string::npos)
      << franka.err;
  const Exit fewer = run_to_exit(kHubEnv, "serve " + kPi0.checkpoint().string() + " --port 0 --custom-embodiment-config " +
                                              write_embodiment(tmp / "arm4.json", 4, 1).string());
  EXPECT_EQ(fewer.code, 2) << fewer.err;
  EXPECT_NE(fewer.err.find("only a padded output, action_dim = max_action_dim 32, is cut to fewer joints"),
            std::string::npos)
      << fewer.err;
  const Exit rtc = run_to_exit(kHubEnv, "serve " + padded.string() + " --port 0 --rtc --custom-embodiment-config " + arm.string());
  EXPECT_EQ(rtc.code, 2) << rtc.err;
  EXPECT_NE(rtc.err.find("keeps 6 of the model's 32 action values"), std::string::npos) << rtc.err;
  // An export carries the embodiment the same rule accepts.
  const Exit exported = run_to_exit(kHubEnv, "export " + padded.string() + " -o " + (tmp / "export").string() +
                                                 " --custom-embodiment-config " + arm.string());
  EXPECT_EQ(exported.code, 0) << exported.err;
}

TEST(Pi0Wedges, ActionGuardClampsPositionAndVelocityAndAudits) {
  Scratch tmp("guard");
  // cam1_stats answers in robot units of tens; the arm allows |x| <= 10 and 20 units/s (2 per step at 10 Hz).
  const fs::path arm = write_embodiment(tmp / "arm.json", 6, 100, 10.0, 20.0);
  const fs::path audit = tmp / "audit.jsonl";
  ServeProcess server(serve_args(kPi0, {"--custom-embodiment-config", arm.string(), "--audit-log", audit.string()}),
                      {kHubEnv});
  wait_ready(server.port());
  const Json a = act_ok(server.port(), kPi0.body("pick up the cube", 2));
  EXPECT_TRUE(a["guard_clamped"].get<bool>());
  ASSERT_FALSE(a["guard_violations"].empty());
  std::set<std::string> limits;
  for (const auto& v : a["guard_violations"]) limits.insert(v["limit"].get<std::string>());
  EXPECT_GT(limits.size(), 1u) << a["guard_violations"];
  for (std::size_t r = 0; r < a["actions"].size(); ++r)
    for (std::size_t j = 0; j < 6; ++j) {
      EXPECT_LE(std::fabs(a["actions"][r][j].get<double>()), 10.0 + 1e-4);
      if (r > 0) {
        EXPECT_LE(std::fabs(a["actions"][r][j].get<double>() - a["actions"][r - 1][j].get<double>()), 2.0 + 1e-4);
      }
    }
  EXPECT_EQ(server.terminate(), 0);
  const std::string log = read(audit);
  EXPECT_NE(log.find(a["request_id"].get<std::string>()), std::string::npos) << log;
}

TEST(Pi0Wedges, AdaptiveStepsStopEarly) {
  ServeProcess server(serve_args(kPi0, {"--adaptive-threshold", "0.5"}), {kHubEnv});
  wait_ready(server.port());
  const Json config = Json::parse(http_get(server.port(), "/config").body);
  EXPECT_EQ(config["num_steps"], 4);
  EXPECT_DOUBLE_EQ(config["wedges"]["adaptive_threshold"].get<double>(), 0.5);
  const Json a = act_ok(server.port(), kPi0.body("pick up the cube", 2));
  EXPECT_GE(a["denoise_steps_used"].get<int>(), 1);
  EXPECT_LT(a["denoise_steps_used"].get<int>(), 4) << a;
  EXPECT_EQ(server.terminate(), 0);
}

TEST(Pi0Wedges, DeadlineAnswersWithTheLastGoodChunk) {
  ServeProcess server(serve_args(kPi0, {"--deadline-ms", "150", "--inject-latency-ms", "700"}), {kHubEnv});
  wait_ready(server.port());
  const Json body = kPi0.body("pick up the cube", 2);
  const HttpReply first = act(server.port(), body);
  EXPECT_EQ(first.status, 504) << first.body;
  EXPECT_EQ(error_code(first), "deadline_exceeded");
  // The late pass finishes in the background and becomes the episode's last good chunk.
  std::this_thread::sleep_for(std::chrono::milliseconds(1200));
  const Json second = act_ok(server.port(), body);
  EXPECT_EQ(second["action_source"], "last_good");
  EXPECT_TRUE(second["deadline_exceeded"].get<bool>());
  EXPECT_GE(second["advanced_steps"].get<int>(), 1);
  EXPECT_EQ(second["actions"].size(), 8u);
  EXPECT_EQ(server.terminate(), 0);
}

TEST(Pi0Wedges, SimilaritySkipReusesTheChunkAtMostKTimes) {
  ServeProcess server(serve_args(kPi0, {"--action-similarity-threshold", "0.01", "--max-similar-skips", "2"}), {kHubEnv});
  wait_ready(server.port());
  Json body = kPi0.body("pick up the cube", 2);
  body["episode_id"] = "ep-1";
  std::vector<std::string> sources;
  std::vector<bool> skipped;
  for (int i = 0; i < 4; ++i) {
    const Json a = act_ok(server.port(), body);
    sources.push_back(a["action_source"]);
    skipped.push_back(a["action_skipped"].get<bool>());
  }
  EXPECT_EQ(sources, (std::vector<std::string>{"model", "cache", "cache", "model"}));
  EXPECT_EQ(skipped, (std::vector<bool>{false, true, true, false}));
  // Another instruction is never similar.
  Json other = body;
  other["instruction"] = "open the drawer";
  EXPECT_EQ(act_ok(server.port(), other)["action_source"], "model");
  EXPECT_EQ(server.terminate(), 0);
}

TEST(Pi0Wedges, CircuitBreakerOpensAfterFailuresAndAProbeClosesIt) {
  Scratch tmp("breaker");
  const fs::path fail = tmp / "fail";
  ServeProcess server(serve_args(kPi0, {"--inject-failure-file", fail.string(), "--max-consecutive-crashes", "2",
                                        "--circuit-reset-ms", "500"}),
                      {kHubEnv});
  wait_ready(server.port());
  const Json body = kPi0.body("pick up the cube", 2);
  std::ofstream(fail) << "x";
  for (int i = 0; i < 2; ++i) {
    const HttpReply r = act(server.port(), body);
    EXPECT_EQ(r.status, 500) << r.body;
    EXPECT_EQ(error_code(r), "inference_failed");
  }
  const HttpReply open = act(server.port(), body);
  EXPECT_EQ(open.status, 503) << open.body;
  EXPECT_EQ(error_code(open), "circuit_open");
  EXPECT_TRUE(open.headers.count("retry-after"));
  const HttpReply health = http_get(server.port(), "/health");
  EXPECT_EQ(health.status, 503);
  EXPECT_EQ(Json::parse(health.body)["state"], "circuit_open");
  fs::remove(fail);
  std::this_thread::sleep_for(std::chrono::milliseconds(700));
  const Json probe = act_ok(server.port(), body);
  EXPECT_EQ(probe["circuit_state"], "closed");
  EXPECT_EQ(http_get(server.port(), "/health").status, 200);
  EXPECT_EQ(server.terminate(), 0);
}

TEST(Pi0Wedges, CloudFallbackAnswersForAFailingServer) {
  Scratch tmp("fallback");
  const fs::path fail = tmp / "fail";
  ServeProcess cloud(serve_args(kPi0), {kHubEnv});
  wait_ready(cloud.port());
  ServeProcess edge(serve_args(kPi0, {"--inject-failure-file", fail.string(), "--cloud-fallback",
                                      "http://127.0.0.1:" + std::to_string(cloud.port())}),
                    {kHubEnv});
  wait_ready(edge.port());
  std::ofstream(fail) << "x";
  const Json body = kPi0.body("pick up the cube", 6);
  const Json a = act_ok(edge.port(), body);
  EXPECT_EQ(a["action_source"], "fallback");
  EXPECT_TRUE(a["fallback_used"].get<bool>());
  EXPECT_FALSE(a["inference_error"].get<std::string>().empty());
  EXPECT_EQ(flat_actions(a), flat_actions(act_ok(cloud.port(), body)));
  EXPECT_EQ(edge.terminate(), 0);
  EXPECT_EQ(cloud.terminate(), 0);
}

TEST(Pi0Wedges, TracesAreRecordedAndReadBack) {
  Scratch tmp("traces");
  const fs::path dir = tmp / "traces";
  std::string first_id;
  {
    ServeProcess server(serve_args(kPi05, {"--record", dir.string(), "--record-fsync", "every_line"}), {kHubEnv});
    wait_ready(server.port());
    first_id = act_ok(server.port(), kPi05.body("pick up the cube", 1))["request_id"];
    act_ok(server.port(), kPi05.body("open the drawer", 2));
    Json bad = kPi05.body("open the drawer", 3);
    bad["state"] = {1};
    EXPECT_EQ(act(server.port(), bad).status, 400);
    EXPECT_EQ(server.terminate(), 0);
  }
  const Exit verify = run_to_exit("", "traces verify --dir " + dir.string());
  EXPECT_EQ(verify.code, 0) << verify.out << verify.err;
  const fs::path out = tmp / "records.json";
  const Exit query = run_to_exit("", "traces query --dir " + dir.string() + " --output " + out.string());
  ASSERT_EQ(query.code, 0) << query.err;
  const Json records = Json::parse(read(out));
  ASSERT_EQ(records.size(), 3u) << records;
  EXPECT_EQ(records[0]["request_id"], first_id);
  EXPECT_EQ(records[0]["task"], "pick up the cube");
  EXPECT_EQ(records[0]["status"], "success");
  EXPECT_EQ(records[0]["actions"].size(), 8u);
  EXPECT_EQ(records[2]["http_status"], 400);
  const Exit summary = run_to_exit("", "traces summary --by task --dir " + dir.string() + " --json");
  ASSERT_EQ(summary.code, 0) << summary.err;
  EXPECT_NE(summary.out.find("open the drawer"), std::string::npos) << summary.out;
  const Exit failed = run_to_exit("", "traces query --status failed --dir " + dir.string());
  EXPECT_NE(failed.out.find("invalid_state"), std::string::npos) << failed.out;
}
