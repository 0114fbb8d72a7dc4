// The HTTP server in-process with a fake engine: health state machine, auth, routing, request ids, the limits,
// queue_full, inference_failed (and serving on), request_timeout, metrics, and stop() draining in-flight requests.
#include <gtest/gtest.h>
#include <unistd.h>

#include <atomic>
#include <filesystem>
#include <condition_variable>
#include <future>
#include <thread>

#include "core/json_util.h"
#include "http_test_client.h"
#include "runtime/trace_reader.h"
#include "serve/base64.h"
#include "serve/msgpack.h"
#include "serve/server.h"
#include "trace_lines.h"
#include "scratch_dir.h"

using namespace tether;
using namespace tether::serve;
using namespace tether::serve::testing;
using namespace std::chrono_literals;

namespace {

// A model with one camera, state 2, action 2, chunk 3, whose actions are state + seed-derived values, so a reply
// can be checked exactly. Knobs make it slow, failing, or blocked at load.
struct FakeEngine {
  std::atomic<int> delay_ms{0};
  std::atomic<bool> fail{false};
  std::atomic<int> calls{0};
  std::mutex mu;
  std::condition_variable cv;
  bool release_load = true;
  std::string embodiment;  // the GR00T-style tag the model serves (empty: none)

  static float expected(float state0, uint64_t seed, int row, int col) {
    return state0 + float(seed % 97) + float(row * 10 + col);
  }

  Engine make() {
    {
      std::unique_lock lock(mu);
      cv.wait(lock, [&] { return release_load; });
    }
    Engine e;
    e.spec.family = "fake";
    e.spec.embodiment = embodiment;
    e.spec.cameras = {"observation.images.front"};
    e.spec.camera_prefix = "observation.images.";
    e.spec.stages = {"preprocess", "vision", "prefix", "denoise"};
    e.spec.state_dim = 2;
    e.spec.action_dim = 2;
    e.spec.chunk_size = 3;
    e.spec.image_height = e.spec.image_width = 4;
    e.model_hash = "sha256:feed";
    e.gemm = "none";
    e.predict = [this](const std::vector<policy::Observation>& batch) {
      ++calls;
      if (delay_ms > 0) std::this_thread::sleep_for(std::chrono::milliseconds(delay_ms.load()));
      if (fail) throw Error(ErrorCode::internal, "fake forward pass failed");
      policy::Prediction p;
      for (const auto& o : batch) {
        policy::ActionChunk c;
        c.chunk_size = 3;
        c.action_dim = 2;
        for (int r = 0; r < 3; ++r)
          for (int k = 0; k < 2; ++k) c.actions.push_back(expected(o.state[0], o.seed, r, k));
        p.items.push_back(std::move(c));
      }
      return p;
    };
    return e;
  }
};

// A server on a free port, run on its own thread; stopped (and joined) at the end of the test.
class TestServer {
 public:
  TestServer(FakeEngine& engine, ServerOptions options = {})
      : TestServer(std::move(options), {{"", [&engine] { return engine.make(); }}}) {}
  // One host per embodiment tag.
  TestServer(ServerOptions options, std::vector<HostLoader> hosts) {
    options.port = 0;
    server_ = std::make_unique<Server>(options, std::move(hosts));
    port_ = server_->start();
    thread_ = std::thread([this] {
      try {
        server_->run(/*handle_signals=*/false);
      } catch (...) {
        error_ = std::current_exception();
      }
    });
  }
  ~TestServer() { stop(); }
  void stop() {
    if (thread_.joinable()) {
      server_->stop();
      thread_.join();
    }
  }
  uint16_t port() const { return port_; }
  Server& server() { return *server_; }
  void wait_ready() {
    for (int i = 0; i < 500 && server_->health() != HealthState::ready; ++i) std::this_thread::sleep_for(10ms);
    ASSERT_EQ(server_->health(), HealthState::ready);
  }

 private:
  std::unique_ptr<Server> server_;
  std::thread thread_;
  uint16_t port_ = 0;
  std::exception_ptr error_;
};

std::string body(float state0, uint64_t seed) {
  std::vector<uint8_t> px(4 * 4 * 3, 100);
  const Json j = {{"instruction", "go"},
                  {"state", {state0, 0}},
                  {"image", {{"data", base64_encode(px.data(), px.size())}, {"shape", {4, 4, 3}}}},
                  {"seed", seed}};
  return j.dump();
}

std::string error_code(const HttpReply& r) { return Json::parse(r.body)["error"]["code"].get<std::string>(); }

// body() as msgpack: raw image bytes, no base64.
std::string msgpack_body(float state0, uint64_t seed) {
  msgpack::Writer w;
  w.map(4);
  w.str("instruction");
  w.str("go");
  w.str("state");
  w.array(2);
  w.float32(state0);
  w.float32(0);
  w.str("image");
  w.map(2);
  w.str("data");
  w.bin(std::string(4 * 4 * 3, '\x64'));
  w.str("shape");
  w.array(3);
  for (int d : {4, 4, 3}) w.integer(d);
  w.str("seed");
  w.integer(int64_t(seed));
  return w.take();
}

}  // namespace

TEST(Server, HealthIsLoadingThenReady) {
  FakeEngine engine;
  engine.release_load = false;
  TestServer srv(engine);
  HttpReply h = http_get(srv.port(), "/health");
  EXPECT_EQ(h.status, 503);
  EXPECT_EQ(Json::parse(h.body)["state"], "loading");
  EXPECT_EQ(Json::parse(h.body)["status"], "unavailable");
  EXPECT_TRUE(Json::parse(h.body)["model_hash"].is_null());
  EXPECT_EQ(http_get(srv.port(), "/ready").status, 503);
  EXPECT_EQ(http_get(srv.port(), "/live").status, 200);
  const HttpReply act = http_post(srv.port(), "/act", body(1, 1));
  EXPECT_EQ(act.status, 503);
  EXPECT_EQ(error_code(act), "not_ready");
  EXPECT_EQ(act.headers.at("retry-after"), "1");
  EXPECT_EQ(error_code(http_get(srv.port(), "/config")), "not_ready");
  {
    std::lock_guard lock(engine.mu);
    engine.release_load = true;
  }
  engine.cv.notify_all();
  srv.wait_ready();
  EXPECT_EQ(engine.calls.load(), 1) << "exactly one warm-up inference";
  h = http_get(srv.port(), "/health");
  EXPECT_EQ(h.status, 200);
  EXPECT_EQ(Json::parse(h.body), Json::parse(R"({"status": "ok", "state": "ready", "model_hash": "sha256:feed"})"));
  EXPECT_EQ(Json::parse(http_get(srv.port(), "/ready").body), Json::parse(R"({"ready": true})"));
}

TEST(Server, ActReturnsTheChunkAndItsMetadata) {
  FakeEngine engine;
  TestServer srv(engine);
  srv.wait_ready();
  const HttpReply r = http_post(srv.port(), "/act", body(2.5f, 7), {{"X-Tether-Request-ID", "robot-1.step:3"}});
  ASSERT_EQ(r.status, 200) << r.body;
  const Json j = Json::parse(r.body);
  ASSERT_EQ(j["actions"].size(), 3u);
  for (int row = 0; row < 3; ++row)
    for (int k = 0; k < 2; ++k) EXPECT_EQ(j["actions"][row][k].get<float>(), FakeEngine::expected(2.5f, 7, row, k));
  EXPECT_EQ(j["num_actions"], 3);
  EXPECT_EQ(j["action_dim"], 2);
  EXPECT_EQ(j["request_id"], "robot-1.step:3");
  EXPECT_EQ(r.headers.at("x-tether-request-id"), "robot-1.step:3");
  EXPECT_EQ(j["model_hash"], "sha256:feed");
  EXPECT_EQ(j["batch_size"], 1);
  EXPECT_TRUE(j["episode_id"].is_null());
  EXPECT_EQ(j["inference_mode"]["backend"], "cpu");
  for (const char* stage : {"total", "queue", "preprocess", "vision", "prefix", "denoise", "postprocess", "predict"})
    EXPECT_TRUE(j["latency_ms"].contains(stage)) << stage;
  EXPECT_LE(j["latency_ms"]["predict"].get<double>(), j["latency_ms"]["total"].get<double>());
}

TEST(Server, DefaultSeedComesFromTheRequestId) {
  FakeEngine engine;
  TestServer srv(engine);
  srv.wait_ready();
  Json b = Json::parse(body(0, 0));
  b.erase("seed");
  const HttpReply r = http_post(srv.port(), "/act", b.dump(), {{"X-Request-ID", "abc"}});
  ASSERT_EQ(r.status, 200) << r.body;
  EXPECT_EQ(Json::parse(r.body)["actions"][0][0].get<float>(), FakeEngine::expected(0, seed_from_request_id("abc"), 0, 0));
}

TEST(Server, RequestIdsAreValidatedOrGenerated) {
  FakeEngine engine;
  TestServer srv(engine);
  EXPECT_EQ(http_get(srv.port(), "/live", {{"X-Request-ID", "up-42"}}).headers.at("x-tether-request-id"), "up-42");
  EXPECT_EQ(http_get(srv.port(), "/live", {{"X-Tether-Request-ID", "a"}, {"X-Request-ID", "b"}})
                .headers.at("x-tether-request-id"),
            "a");
  for (const std::string& bad : {std::string("has space"), std::string(129, 'x'), std::string("semi;colon")}) {
    const std::string id = http_get(srv.port(), "/live", {{"X-Tether-Request-ID", bad}}).headers.at("x-tether-request-id");
    EXPECT_NE(id, bad);
    EXPECT_TRUE(valid_request_id(id)) << id;
  }
  const std::string a = http_get(srv.port(), "/nope").headers.at("x-tether-request-id");
  const std::string b = http_get(srv.port(), "/nope").headers.at("x-tether-request-id");
  EXPECT_NE(a, b);
}

TEST(Server, AuthGuardsActAndConfigOnly) {
  FakeEngine engine;
  ServerOptions o;
  o.api_key = "s3cret-key";
  TestServer srv(engine, o);
  srv.wait_ready();
  for (const auto& headers : std::vector<std::vector<std::pair<std::string, std::string>>>{
           {}, {{"Authorization", "Bearer wrong"}}, {{"X-Tether-Key", "s3cret-ke"}}, {{"Authorization", "s3cret-key"}}}) {
    const HttpReply r = http_post(srv.port(), "/act", body(1, 1), headers);
    EXPECT_EQ(r.status, 401);
    EXPECT_EQ(error_code(r), "unauthorized");
    EXPECT_EQ(http_get(srv.port(), "/config", headers).status, 401);
  }
  const int calls_before = engine.calls.load();
  EXPECT_EQ(http_post(srv.port(), "/act", body(1, 1), {{"Authorization", "Bearer s3cret-key"}}).status, 200);
  EXPECT_EQ(http_post(srv.port(), "/act", body(1, 1), {{"X-Tether-Key", "s3cret-key"}}).status, 200);
  EXPECT_EQ(engine.calls.load(), calls_before + 2) << "unauthorized requests must run nothing";
  EXPECT_EQ(http_get(srv.port(), "/config", {{"X-Tether-Key", "s3cret-key"}}).status, 200);
  for (const char* path : {"/health", "/ready", "/live", "/metrics"}) EXPECT_EQ(http_get(srv.port(), path).status, 200) << path;
}

TEST(Server, RoutingErrors) {
  FakeEngine engine;
  TestServer srv(engine);
  srv.wait_ready();
  HttpReply r = http_get(srv.port(), "/nope");
  EXPECT_EQ(r.status, 404);
  EXPECT_EQ(error_code(r), "not_found");
  EXPECT_EQ(r.headers.at("content-type"), "application/json");
  r = http_get(srv.port(), "/act");
  EXPECT_EQ(r.status, 405);
  EXPECT_EQ(error_code(r), "method_not_allowed");
  EXPECT_EQ(http_post(srv.port(), "/health", "{}").status, 405);
  r = http_post(srv.port(), "/act", "{not json");
  EXPECT_EQ(r.status, 400);
  EXPECT_EQ(error_code(r), "bad_json");
}

TEST(Server, BodyAndHeaderLimits) {
  FakeEngine engine;
  ServerOptions o;
  o.max_body_bytes = 2048;
  o.max_header_bytes = 1024;
  TestServer srv(engine, o);
  srv.wait_ready();
  HttpReply r = http_post(srv.port(), "/act", std::string(4096, ' '), {{"X-Tether-Request-ID", "big-1"}});
  EXPECT_EQ(r.status, 413);
  EXPECT_EQ(error_code(r), "body_too_large");
  EXPECT_EQ(r.headers.at("x-tether-request-id"), "big-1");
  r = http_get(srv.port(), "/health", {{"X-Padding", std::string(2000, 'a')}});
  EXPECT_EQ(r.status, 431);
  EXPECT_EQ(error_code(r), "header_too_large");
  EXPECT_EQ(http_get(srv.port(), "/health", {{"X-Padding", std::string(500, 'a')}}).status, 200);
}

TEST(Server, FullQueueAnswers503WithRetryAfter) {
  FakeEngine engine;
  ServerOptions o;
  o.batch = {.max_batch = 1, .batch_timeout_ms = 0, .max_queue = 1};
  TestServer srv(engine, o);
  srv.wait_ready();
  engine.delay_ms = 300;
  std::vector<std::future<HttpReply>> replies;
  for (int i = 0; i < 6; ++i) {
    replies.push_back(std::async(std::launch::async, [&, i] { return http_post(srv.port(), "/act", body(float(i), i)); }));
    std::this_thread::sleep_for(20ms);
  }
  int ok = 0, full = 0;
  for (auto& f : replies) {
    const HttpReply r = f.get();
    if (r.status == 200) {
      ++ok;
    } else {
      EXPECT_EQ(r.status, 503);
      EXPECT_EQ(error_code(r), "queue_full");
      EXPECT_EQ(r.headers.at("retry-after"), "1");
      ++full;
    }
  }
  EXPECT_GE(ok, 2);  // one running, one queued
  EXPECT_GE(full, 1);
}

TEST(Server, InferenceFailureIs500AndTheServerKeepsServing) {
  FakeEngine engine;
  TestServer srv(engine);
  srv.wait_ready();
  engine.fail = true;
  HttpReply r = http_post(srv.port(), "/act", body(1, 1));
  EXPECT_EQ(r.status, 500);
  EXPECT_EQ(error_code(r), "inference_failed");
  EXPECT_NE(Json::parse(r.body)["error"]["message"].get<std::string>().find("fake forward pass failed"), std::string::npos);
  EXPECT_EQ(http_get(srv.port(), "/health").status, 200) << "one failed batch is not a sick server";
  for (int i = 0; i < 3; ++i) http_post(srv.port(), "/act", body(1, 1));
  r = http_get(srv.port(), "/health");
  EXPECT_EQ(r.status, 503);
  EXPECT_EQ(Json::parse(r.body)["state"], "degraded");
  engine.fail = false;
  EXPECT_EQ(http_post(srv.port(), "/act", body(1, 1)).status, 200) << "a degraded server still tries";
  EXPECT_EQ(http_get(srv.port(), "/health").status, 200);
}

TEST(Server, FailedWarmUpIsDegradedUntilAForwardPassSucceeds) {
  FakeEngine engine;
  engine.fail = true;
  TestServer srv(engine);
  for (int i = 0; i < 500 && srv.server().health() != HealthState::degraded; ++i) std::this_thread::sleep_for(10ms);
  HttpReply h = http_get(srv.port(), "/health");
  EXPECT_EQ(h.status, 503);
  EXPECT_EQ(Json::parse(h.body)["state"], "degraded");
  EXPECT_EQ(Json::parse(h.body)["model_hash"], "sha256:feed");
  EXPECT_EQ(http_get(srv.port(), "/ready").status, 503);
  engine.fail = false;
  EXPECT_EQ(http_post(srv.port(), "/act", body(1, 1)).status, 200) << "a degraded server still serves /act";
  h = http_get(srv.port(), "/health");
  EXPECT_EQ(h.status, 200);
  EXPECT_EQ(Json::parse(h.body)["state"], "ready");
}

TEST(Server, QueuedPastTheRequestTimeoutIs408) {
  FakeEngine engine;
  ServerOptions o;
  o.batch = {.max_batch = 1, .batch_timeout_ms = 0, .max_queue = 8};
  o.request_timeout_ms = 100;
  TestServer srv(engine, o);
  srv.wait_ready();
  engine.delay_ms = 300;
  const int before = engine.calls;
  auto slow = std::async(std::launch::async, [&] { return http_post(srv.port(), "/act", body(0, 0)); });
  // The second request must arrive while the first is in the engine, however slow the machine (or emulator) is.
  for (int i = 0; i < 1000 && engine.calls == before; ++i) std::this_thread::sleep_for(5ms);
  ASSERT_GT(engine.calls, before) << "the first request never reached the engine";
  const HttpReply late = http_post(srv.port(), "/act", body(1, 1));
  EXPECT_EQ(late.status, 408);
  EXPECT_EQ(error_code(late), "request_timeout");
  EXPECT_EQ(slow.get().status, 200);
}

TEST(Server, MetricsCountRequestsAndStages) {
  FakeEngine engine;
  TestServer srv(engine);
  srv.wait_ready();
  http_post(srv.port(), "/act", body(1, 1));
  http_post(srv.port(), "/act", "[]");
  http_get(srv.port(), "/nope");
  const HttpReply m = http_get(srv.port(), "/metrics");
  ASSERT_EQ(m.status, 200);
  EXPECT_EQ(m.headers.at("content-type").rfind("text/plain; version=0.0.4", 0), 0u);
  for (const char* line : {"tether_requests_total{transport=\"http\",endpoint=\"/act\",status=\"200\"} 1",
                           "tether_requests_total{transport=\"http\",endpoint=\"/act\",status=\"400\"} 1",
                           "tether_requests_total{transport=\"http\",endpoint=\"other\",status=\"404\"} 1",
                           "tether_request_duration_seconds_count{stage=\"denoise\"} 1",
                           "tether_batch_size_count 1",  // the warm-up is not a served request
                           "tether_model_ready 1", "tether_queue_depth 0", "tether_build_info{version="})
    EXPECT_NE(m.body.find(line), std::string::npos) << line << "\n" << m.body;
}

TEST(Server, EachEmbodimentHasItsOwnWedgeMetrics) {
  FakeEngine arm, humanoid;
  arm.embodiment = "arm";
  humanoid.embodiment = "humanoid";
  ServerOptions o;
  o.wedges.similarity_threshold = 0.5;
  o.wedges.max_similar_skips = 3;
  TestServer srv(o, {{"arm", [&arm] { return arm.make(); }}, {"humanoid", [&humanoid] { return humanoid.make(); }}});
  srv.wait_ready();
  Json b = Json::parse(body(1, 1));
  b["embodiment_tag"] = "arm";
  for (int i = 0; i < 2; ++i) {  // the second time, the same observation is answered from the cache
    const HttpReply r = http_post(srv.port(), "/act", b.dump());
    ASSERT_EQ(r.status, 200) << r.body;
  }
  const std::string m = http_get(srv.port(), "/metrics").body;
  for (const char* line : {"tether_action_skip_total{embodiment=\"arm\"} 1", "tether_action_skip_total{embodiment=\"humanoid\"} 0",
                           "tether_episodes{embodiment=\"arm\"} 1", "tether_episodes{embodiment=\"humanoid\"} 0",
                           "tether_model_ready 1"})
    EXPECT_NE(m.find(std::string(line) + "\n"), std::string::npos) << line << "\n" << m;
  EXPECT_EQ(m.find("\ntether_action_skip_total "), std::string::npos) << "no series without its embodiment\n" << m;
  EXPECT_EQ(arm.calls.load(), 2) << "warm-up and the first request";
}

TEST(Server, StopFinishesInFlightRequests) {
  FakeEngine engine;
  TestServer srv(engine);
  srv.wait_ready();
  engine.delay_ms = 300;
  auto in_flight = std::async(std::launch::async, [&] { return http_post(srv.port(), "/act", body(3, 3)); });
  std::this_thread::sleep_for(100ms);
  srv.stop();  // returns once the server has drained
  const HttpReply r = in_flight.get();
  EXPECT_EQ(r.status, 200);
  EXPECT_EQ(r.headers.at("connection"), "close");
  EXPECT_THROW(http_get(srv.port(), "/live"), std::exception) << "still accepting after stop";
}

TEST(Server, LoadFailureIsRethrownFromRun) {
  ServerOptions o;
  o.port = 0;
  Server server(o, []() -> Engine { throw Error(ErrorCode::not_found, "no such checkpoint"); });
  server.start();
  try {
    server.run(false);
    FAIL() << "run() returned normally";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("no such checkpoint"), std::string::npos);
  }
}

TEST(Server, ConcurrentKeepAliveClientsNeverStall) {
  // Many keep-alive connections served by several I/O threads, every request answered, and correctly. A stalled
  // connection shows as a failed read (the server drops a connection idle past its read timeout), not as a time.
  FakeEngine engine;
  engine.delay_ms = 2;
  ServerOptions o;
  o.threads = 4;
  o.read_timeout_ms = 3000;
  TestServer srv(engine, o);
  srv.wait_ready();
  namespace net = boost::asio;
  namespace http = boost::beast::http;
  constexpr int kClients = 16, kRequests = 60;
  std::atomic<int> ok{0};
  std::vector<std::thread> clients;
  for (int c = 0; c < kClients; ++c)
    clients.emplace_back([&, c] {
      net::io_context ioc;
      boost::beast::tcp_stream stream(ioc);
      stream.connect(net::ip::tcp::endpoint(net::ip::make_address("127.0.0.1"), srv.port()));
      boost::beast::flat_buffer buffer;
      for (int i = 0; i < kRequests; ++i) {
        http::request<http::string_body> req{http::verb::post, "/act", 11};
        req.set(http::field::host, "127.0.0.1");
        req.body() = body(float(c), uint64_t(c * 1000 + i));
        req.prepare_payload();
        http::write(stream, req);
        http::response<http::string_body> res;
        boost::beast::error_code ec;
        http::read(stream, buffer, res, ec);
        if (ec) return;
        if (res.result_int() == 200) ++ok;
      }
    });
  for (auto& t : clients) t.join();
  EXPECT_EQ(ok.load(), kClients * kRequests);
}

TEST(Server, ActTakesMsgpackBodiesAndAnswersInTheFormatAccepted) {
  const auto dir = tether::testing::scratch_dir() / "msgpack_trace";
  std::filesystem::remove_all(dir);
  FakeEngine engine;
  ServerOptions o;
  o.max_body_bytes = 4096;
  runtime::TraceOptions t;
  t.dir = dir.string();
  t.fsync = runtime::TraceOptions::Fsync::every_line;
  o.wedges.record = t;
  using Headers = std::vector<std::pair<std::string, std::string>>;
  const auto msgpack_headers = [](const std::string& id, const std::string& accept) {
    return Headers{{"Content-Type", "application/msgpack"}, {"Accept", accept}, {"X-Tether-Request-ID", id}};
  };
  {
    TestServer srv(engine, o);
    srv.wait_ready();
    // The same request as JSON and as msgpack: the same actions.
    const HttpReply as_json = http_post(srv.port(), "/act", body(2, 11));
    HttpReply r = http_post(srv.port(), "/act", msgpack_body(2, 11), msgpack_headers("mp-json", "application/json"));
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_EQ(r.headers.at("content-type"), "application/json");
    EXPECT_EQ(Json::parse(r.body)["actions"], Json::parse(as_json.body)["actions"]);
    // Accept: msgpack (among others, with parameters): the answer is a msgpack map, actions as float32.
    r = http_post(srv.port(), "/act", msgpack_body(2, 11),
                  msgpack_headers("mp-mp", "application/json;q=0.5, Application/MsgPack; q=1"));
    ASSERT_EQ(r.status, 200);
    EXPECT_EQ(r.headers.at("content-type"), "application/msgpack");
    const msgpack::Value answer = msgpack::parse(r.body);
    EXPECT_EQ(answer.find("request_id")->bytes, "mp-mp");
    EXPECT_EQ(answer.find("actions")->items.size(), 3u);
    EXPECT_EQ(answer.find("actions")->items[1].items[0].kind, msgpack::Kind::float32);
    EXPECT_EQ(answer.find("actions")->items[1].items[0].number, FakeEngine::expected(2, 11, 1, 0));

    // Bad input: the usual stable codes, in the format the client accepts.
    r = http_post(srv.port(), "/act", "\x81\xa5sta", msgpack_headers("truncated", "application/json"));
    EXPECT_EQ(r.status, 400);
    EXPECT_EQ(error_code(r), "bad_msgpack");
    r = http_post(srv.port(), "/act", body(1, 1), msgpack_headers("json-as-msgpack", "application/msgpack"));
    EXPECT_EQ(r.status, 400);
    EXPECT_EQ(r.headers.at("content-type"), "application/msgpack");
    EXPECT_EQ(msgpack::parse(r.body).find("error")->find("code")->bytes, "bad_msgpack");
    msgpack::Writer wrong;
    wrong.map(1);
    wrong.str("state");
    wrong.str("0,0");
    r = http_post(srv.port(), "/act", wrong.take(), msgpack_headers("wrong-type", "application/json"));
    EXPECT_EQ(r.status, 400);
    EXPECT_EQ(error_code(r), "missing_field");  // no instruction: the first check
    msgpack::Writer state_text;
    state_text.map(2);
    state_text.str("instruction");
    state_text.str("go");
    state_text.str("state");
    state_text.str("0,0");
    r = http_post(srv.port(), "/act", state_text.take(), msgpack_headers("state-text", "application/json"));
    EXPECT_EQ(r.status, 400);
    EXPECT_EQ(error_code(r), "invalid_field");
    r = http_post(srv.port(), "/act", std::string(8192, '\x90'), msgpack_headers("huge", "application/msgpack"));
    EXPECT_EQ(r.status, 413);
    EXPECT_EQ(error_code(r), "body_too_large");  // refused while reading, before the format is known: JSON
    // Still serving.
    r = http_post(srv.port(), "/act", msgpack_body(3, 4), msgpack_headers("after", "application/json"));
    EXPECT_EQ(r.status, 200);
    const std::string metrics = http_get(srv.port(), "/metrics").body;
    EXPECT_NE(metrics.find("tether_requests_total{transport=\"http\",endpoint=\"/act\",status=\"400\"} 4"),
              std::string::npos)
        << metrics;
  }
  // One line per request that reached the pipeline (the 413 did not), refusals included; the chain verifies.
  const std::vector<Json> lines = read_trace_lines(dir);
  ASSERT_EQ(lines.size(), 8u);
  const std::vector<std::pair<std::string, std::string>> refused = {
      {"truncated", "bad_msgpack"}, {"json-as-msgpack", "bad_msgpack"}, {"wrong-type", "missing_field"},
      {"state-text", "invalid_field"}};
  for (std::size_t i = 0; i < refused.size(); ++i) {
    const Json& line = lines[i + 3];
    EXPECT_EQ(line["request_id"], refused[i].first);
    EXPECT_EQ(line["transport"], "http");
    EXPECT_EQ(line["http_status"], 400);
    EXPECT_EQ(line["error"]["code"], refused[i].second) << line.dump();
  }
  EXPECT_EQ(lines[7]["request_id"], "after");
  EXPECT_EQ(lines[7]["status"], "success");
  const runtime::TraceVerifyReport report = runtime::verify_traces(dir.string());
  EXPECT_TRUE(report.ok()) << report.problem->message;
  std::filesystem::remove_all(dir);
}
