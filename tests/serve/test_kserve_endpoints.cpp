// The /v2 endpoints in-process with a fake engine: health and metadata, JSON and binary infer, a batch of two
// sharing one forward pass, the model name and version, the API key, item errors, the transport's metrics and the
// trace lines of requests refused while decoding.
#include <gtest/gtest.h>

#include <unistd.h>

#include <atomic>
#include <cstring>
#include <filesystem>
#include <thread>

#include "core/json_util.h"
#include "http_test_client.h"
#include "runtime/trace_reader.h"
#include "serve/server.h"
#include "trace_lines.h"
#include "scratch_dir.h"

using namespace tether;
using namespace tether::serve;
using namespace tether::serve::testing;
using namespace std::chrono_literals;

namespace {

// State 2, action 2, chunk 3; actions are state[0] + row * 10 + col; the last batch size is kept.
struct FakeModel {
  std::atomic<int> last_batch{0};
  Engine make() {
    Engine e;
    e.spec.family = "fake";
    e.spec.cameras = {"observation.images.front"};
    e.spec.camera_prefix = "observation.images.";
    e.spec.stages = {"preprocess", "denoise"};
    e.spec.state_dim = 2;
    e.spec.action_dim = 2;
    e.spec.chunk_size = 3;
    e.spec.image_height = e.spec.image_width = 4;
    e.model_hash = "sha256:feed";
    e.model_name = "fake-dir";
    e.gemm = "none";
    e.predict = [this](const std::vector<policy::Observation>& batch) {
      last_batch = int(batch.size());
      policy::Prediction p;
      for (const auto& o : batch) {
        policy::ActionChunk c;
        c.chunk_size = 3;
        c.action_dim = 2;
        for (int r = 0; r < 3; ++r)
          for (int k = 0; k < 2; ++k) c.actions.push_back(o.state[0] + float(r * 10 + k));
        p.items.push_back(std::move(c));
      }
      return p;
    };
    return e;
  }
};

class V2Server {
 public:
  explicit V2Server(ServerOptions o = {}) {
    o.port = 0;
    server_ = std::make_unique<Server>(o, [this] { return model.make(); });
    port_ = server_->start();
    thread_ = std::thread([this] { server_->run(false); });
    for (int i = 0; i < 500 && server_->health() != HealthState::ready; ++i) std::this_thread::sleep_for(10ms);
  }
  ~V2Server() {
    server_->stop();
    thread_.join();
  }
  uint16_t port() const { return port_; }
  FakeModel model;

 private:
  std::unique_ptr<Server> server_;
  std::thread thread_;
  uint16_t port_ = 0;
};

Json tensor(const std::string& name, const std::string& datatype, std::vector<int64_t> shape, Json data) {
  return {{"name", name}, {"datatype", datatype}, {"shape", std::move(shape)}, {"data", std::move(data)}};
}

// `n` items, item i with state [10 * i + 1, 0].
Json infer_json(int n) {
  Json instr = Json::array(), state = Json::array(), px = Json::array();
  for (int i = 0; i < n; ++i) {
    instr.push_back("go");
    state.push_back(10.0 * i + 1);
    state.push_back(0.0);
    for (int k = 0; k < 4 * 4 * 3; ++k) px.push_back(100);
  }
  return {{"id", "r1"},
          {"inputs",
           {tensor("instruction", "BYTES", {n}, instr), tensor("state", "FP32", {n, 2}, state),
            tensor("image.front", "UINT8", {n, 4, 4, 3}, px)}}};
}

std::string v2_error(const HttpReply& r) { return Json::parse(r.body).at("error").get<std::string>(); }

}  // namespace

TEST(ServerKServeEndpoints, HealthAndMetadata) {
  ServerOptions o;
  o.model_name = "demo";
  V2Server s(o);
  EXPECT_EQ(http_get(s.port(), "/v2/health/live").status, 200);
  const HttpReply ready = http_get(s.port(), "/v2/health/ready");
  EXPECT_EQ(ready.status, 200);
  EXPECT_TRUE(ready.body.empty());
  EXPECT_EQ(http_get(s.port(), "/v2/models/demo/ready").status, 200);
  EXPECT_EQ(http_get(s.port(), "/v2/models/demo/versions/1/ready").status, 200);
  const Json server = Json::parse(http_get(s.port(), "/v2").body);
  EXPECT_EQ(server["name"], "tether");
  EXPECT_EQ(server["extensions"], Json({"binary_tensor_data"}));
  const HttpReply meta = http_get(s.port(), "/v2/models/demo");
  ASSERT_EQ(meta.status, 200) << meta.body;
  const Json m = Json::parse(meta.body);
  EXPECT_EQ(m["name"], "demo");
  EXPECT_EQ(m["outputs"][0]["shape"], Json({-1, 3, 2}));
  EXPECT_EQ(m["inputs"][2]["name"], "image.front");

  const HttpReply unknown = http_get(s.port(), "/v2/models/other");
  EXPECT_EQ(unknown.status, 404);
  EXPECT_NE(v2_error(unknown).find("unknown model 'other'"), std::string::npos);
  EXPECT_EQ(http_get(s.port(), "/v2/models/demo/versions/2").status, 404);
  EXPECT_EQ(http_get(s.port(), "/v2/models/other/ready").status, 404);
  EXPECT_EQ(http_get(s.port(), "/v2/nothing").status, 404);
  EXPECT_EQ(http_post(s.port(), "/v2/health/live", "").status, 405);
  EXPECT_EQ(http_get(s.port(), "/v2/models/demo/infer").status, 405);
}

TEST(ServerKServeEndpoints, DefaultNameIsTheCheckpointDirectory) {
  V2Server s;
  EXPECT_EQ(http_get(s.port(), "/v2/models/fake-dir").status, 200);
}

TEST(ServerKServeEndpoints, InferJsonAndABatchOfTwo) {
  ServerOptions o;
  o.model_name = "demo";
  o.batch.batch_timeout_ms = 200;  // the two items reach the batcher together
  V2Server s(o);
  HttpReply r = http_post(s.port(), "/v2/models/demo/infer", infer_json(1).dump());
  ASSERT_EQ(r.status, 200) << r.body;
  Json j = Json::parse(r.body);
  EXPECT_EQ(j["id"], "r1");
  EXPECT_EQ(j["model_name"], "demo");
  EXPECT_EQ(j["outputs"][0]["name"], "actions");
  EXPECT_EQ(j["outputs"][0]["shape"], Json({1, 3, 2}));
  EXPECT_EQ(j["outputs"][0]["data"], Json({1.0, 2.0, 11.0, 12.0, 21.0, 22.0}));
  EXPECT_EQ(j["outputs"][1]["data"], Json({"model"}));

  r = http_post(s.port(), "/v2/models/demo/versions/1/infer", infer_json(2).dump());
  ASSERT_EQ(r.status, 200) << r.body;
  j = Json::parse(r.body);
  EXPECT_EQ(j["outputs"][0]["shape"], Json({2, 3, 2}));
  EXPECT_EQ(j["outputs"][0]["data"][6], 11.0);  // item 1's first action: state 11
  EXPECT_EQ(s.model.last_batch.load(), 2);
  // The server's and the forward pass's time, as scalar parameters.
  ASSERT_TRUE(j["parameters"]["tether_total_ms"].is_number()) << j.dump();
  ASSERT_TRUE(j["parameters"]["tether_predict_ms"].is_number()) << j.dump();
  EXPECT_GT(j["parameters"]["tether_total_ms"].get<double>(), 0.0);
  EXPECT_LE(j["parameters"]["tether_predict_ms"].get<double>(), j["parameters"]["tether_total_ms"].get<double>());

  const std::string metrics = http_get(s.port(), "/metrics").body;
  EXPECT_NE(metrics.find("tether_requests_total{transport=\"kserve\",endpoint=\"/v2/models/{name}/infer\",status=\"200\"} 3"),
            std::string::npos)
      << metrics;
}

TEST(ServerKServeEndpoints, InferBinaryOutputs) {
  ServerOptions o;
  o.model_name = "demo";
  V2Server s(o);
  Json req = infer_json(1);
  req["outputs"] = {{{"name", "actions"}, {"parameters", {{"binary_data", true}}}}};
  const HttpReply r = http_post(s.port(), "/v2/models/demo/infer", req.dump());
  ASSERT_EQ(r.status, 200) << r.body;
  ASSERT_EQ(r.headers.count("inference-header-content-length"), 1u);
  const std::size_t n = std::stoul(r.headers.at("inference-header-content-length"));
  const Json h = Json::parse(r.body.substr(0, n));
  ASSERT_EQ(h["outputs"].size(), 1u);
  EXPECT_EQ(h["outputs"][0]["parameters"]["binary_data_size"], 24);
  ASSERT_EQ(r.body.size(), n + 24);
  float f[6];
  std::memcpy(f, r.body.data() + n, 24);
  EXPECT_EQ(f[5], 22.0f);
}

TEST(ServerKServeEndpoints, ErrorsInTheProtocolsForm) {
  ServerOptions o;
  o.model_name = "demo";
  o.api_key = "s3cret";
  V2Server s(o);
  // Health stays open; metadata and infer need the key, as /config and /act do.
  EXPECT_EQ(http_get(s.port(), "/v2/health/ready").status, 200);
  EXPECT_EQ(http_get(s.port(), "/v2/models/demo").status, 401);
  HttpReply r = http_post(s.port(), "/v2/models/demo/infer", infer_json(1).dump());
  EXPECT_EQ(r.status, 401);
  EXPECT_NE(v2_error(r).find("API key"), std::string::npos) << r.body;
  const std::vector<std::pair<std::string, std::string>> key = {{"Authorization", "Bearer s3cret"}};
  EXPECT_EQ(http_get(s.port(), "/v2/models/demo", key).status, 200);
  r = http_post(s.port(), "/v2/models/demo/infer", "{not json", key);
  EXPECT_EQ(r.status, 400);
  EXPECT_NE(v2_error(r).find("not valid JSON"), std::string::npos);
  Json bad = infer_json(2);
  bad["inputs"][1]["data"][3] = 1e39;  // item 1's state is not finite
  r = http_post(s.port(), "/v2/models/demo/infer", bad.dump(), {{"X-Tether-Key", "s3cret"}});
  EXPECT_EQ(r.status, 400);
  EXPECT_NE(v2_error(r).find("item 1: state[1]"), std::string::npos) << r.body;
  const std::string metrics = http_get(s.port(), "/metrics").body;
  EXPECT_NE(metrics.find("transport=\"kserve\",endpoint=\"/v2/models/{name}/infer\",status=\"401\"} 1"), std::string::npos)
      << metrics;
}

TEST(ServerKServeEndpoints, RequestsRefusedWhileDecodingLeaveATraceLine) {
  const auto dir = tether::testing::scratch_dir() / "kserve_trace";
  std::filesystem::remove_all(dir);
  ServerOptions o;
  o.model_name = "demo";
  runtime::TraceOptions t;
  t.dir = dir.string();
  t.fsync = runtime::TraceOptions::Fsync::every_line;
  o.wedges.record = t;
  using Headers = std::vector<std::pair<std::string, std::string>>;
  const auto id = [](const std::string& v) { return Headers{{"X-Tether-Request-ID", v}}; };
  {
    V2Server s(o);
    ASSERT_EQ(http_post(s.port(), "/v2/models/demo/infer", infer_json(1).dump(), id("good")).status, 200);
    Json wrong_shape = infer_json(1);
    wrong_shape["inputs"][1]["shape"] = {1, 3};
    Json wrong_dtype = infer_json(1);
    wrong_dtype["inputs"][1]["datatype"] = "FP64";
    auto bad_header = id("bad-header");
    bad_header.emplace_back("Inference-Header-Content-Length", "999");
    for (const HttpReply& reply :
         {http_post(s.port(), "/v2/models/demo/infer", "{not json", id("bad-json")),
          http_post(s.port(), "/v2/models/demo/infer", infer_json(1).dump(), bad_header),
          http_post(s.port(), "/v2/models/demo/infer", wrong_shape.dump(), id("bad-shape")),
          http_post(s.port(), "/v2/models/demo/infer", wrong_dtype.dump(), id("bad-dtype"))})
      EXPECT_EQ(reply.status, 400) << reply.body;
    // Refused before the body is read: no line.
    EXPECT_EQ(http_post(s.port(), "/v2/models/other/infer", "{not json", id("bad-model")).status, 404);
    const std::string metrics = http_get(s.port(), "/metrics").body;
    EXPECT_NE(metrics.find("transport=\"kserve\",endpoint=\"/v2/models/{name}/infer\",status=\"400\"} 4"),
              std::string::npos)
        << metrics;
  }
  const std::vector<Json> lines = read_trace_lines(dir);
  ASSERT_EQ(lines.size(), 5u);
  EXPECT_EQ(lines[0]["request_id"], "good");
  EXPECT_EQ(lines[0]["status"], "success");
  const std::vector<std::pair<std::string, std::string>> expected = {
      {"bad-json", "bad_json"}, {"bad-header", "invalid_field"}, {"bad-shape", "invalid_state"},
      {"bad-dtype", "invalid_field"}};
  for (std::size_t i = 0; i < expected.size(); ++i) {
    const Json& line = lines[i + 1];
    EXPECT_EQ(line["request_id"], expected[i].first);
    EXPECT_EQ(line["transport"], "kserve");
    EXPECT_EQ(line["status"], "failed");
    EXPECT_EQ(line["http_status"], 400);
    EXPECT_EQ(line["error"]["code"], expected[i].second) << line.dump();
  }
  EXPECT_NE(lines[2]["error"]["message"].get<std::string>().find("Inference-Header-Content-Length"), std::string::npos);
  EXPECT_NE(lines[3]["error"]["message"].get<std::string>().find("input 'state'"), std::string::npos);
  // The refusals extend the hash chain: the earlier line is intact and the chain verifies.
  const runtime::TraceVerifyReport report = runtime::verify_traces(dir.string());
  EXPECT_TRUE(report.ok()) << report.problem->message;
  EXPECT_EQ(report.lines, 5u);
  std::filesystem::remove_all(dir);
}
