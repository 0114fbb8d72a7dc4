// The /act pipeline called directly, as a non-HTTP transport would: answers, auth, readiness, the body limit, the
// fallback marker, metrics and the trace line, with no socket in between.
#include <gtest/gtest.h>
#include <unistd.h>

#include <boost/asio.hpp>
#include <filesystem>

#include "core/error.h"
#include "serve/act_pipeline.h"
#include "serve/base64.h"
#include "trace_lines.h"
#include "scratch_dir.h"

using namespace tether;
using namespace tether::serve;
namespace net = boost::asio;

namespace {

// State 2, action 2, chunk 3: actions are state[0] + row * 10 + col, so a reply is checked exactly.
Engine fake_engine(std::shared_ptr<std::atomic<bool>> fail) {
  Engine e;
  e.spec.family = "fake";
  e.spec.cameras = {"observation.images.front"};
  e.spec.state_dim = 2;
  e.spec.action_dim = 2;
  e.spec.chunk_size = 3;
  e.spec.image_height = e.spec.image_width = 4;
  e.model_hash = "sha256:feed";
  e.model_name = "fake-model";
  e.gemm = "none";
  e.predict = [fail](const std::vector<policy::Observation>& batch) {
    if (*fail) throw Error(ErrorCode::internal, "fake forward pass failed");
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

std::string act_body(float state0) {
  std::vector<uint8_t> px(4 * 4 * 3, 100);
  const Json j = {{"instruction", "go"},
                  {"state", {state0, 0}},
                  {"image", {{"data", base64_encode(px.data(), px.size())}, {"shape", {4, 4, 3}}}},
                  {"seed", 1}};
  return j.dump();
}

// One /act body through the pipeline, as a transport would run it.
ActResponse run_body(ActPipeline& pipeline, const std::string& body, RequestContext ctx = {}) {
  if (ctx.request_id.empty()) ctx.request_id = "req-1";
  ctx.received = std::chrono::steady_clock::now();
  net::io_context ioc;
  auto future = net::co_spawn(ioc, pipeline.run(body, ctx), net::use_future);
  ioc.run();
  return future.get();
}

// A pipeline over a host loaded in the constructor (or not, with load = false).
struct Fixture {
  explicit Fixture(ServerOptions o = {}, bool load = true)
      : opts(std::move(o)),
        metrics("test", ""),
        hosts({{"", [f = fail] { return fake_engine(f); }}}, opts.batch, opts.wedges, metrics),
        host(hosts.primary()),
        pipeline(opts, hosts, metrics) {
    if (load) {
      EXPECT_TRUE(host.load());
    }
  }
  ~Fixture() { host.stop(); }

  ActResponse run(const std::string& body, RequestContext ctx = {}) { return run_body(pipeline, body, std::move(ctx)); }

  std::shared_ptr<std::atomic<bool>> fail = std::make_shared<std::atomic<bool>>(false);
  ServerOptions opts;
  Metrics metrics;
  ModelHosts hosts;
  ModelHost& host;
  ActPipeline pipeline;
};

std::string code_of(const ActResponse& r) { return r.body["error"]["code"].get<std::string>(); }

}  // namespace

TEST(ActPipeline, AnswersWithTheChunkAndCountsTheRequest) {
  Fixture f;
  const ActResponse r = f.run(act_body(5));
  ASSERT_EQ(r.status, 200) << r.body.dump();
  EXPECT_TRUE(r.ok());
  EXPECT_EQ(r.body["num_actions"], 3);
  EXPECT_EQ(r.body["actions"][2][1].get<float>(), 5 + 21);
  EXPECT_EQ(r.body["request_id"], "req-1");
  EXPECT_EQ(r.body["model_hash"], "sha256:feed");
  EXPECT_NE(f.metrics.render().find("tether_requests_total{transport=\"http\",endpoint=\"/act\",status=\"200\"} 1"), std::string::npos);
}

TEST(ActPipeline, ErrorsAreResponsesNotExceptions) {
  Fixture f;
  ActResponse r = f.run("{not json");
  EXPECT_EQ(r.status, 400);
  EXPECT_EQ(code_of(r), "bad_json");
  *f.fail = true;
  r = f.run(act_body(0));
  EXPECT_EQ(r.status, 500);
  EXPECT_EQ(code_of(r), "inference_failed");
  const std::string m = f.metrics.render();
  EXPECT_NE(m.find("tether_requests_total{transport=\"http\",endpoint=\"/act\",status=\"400\"} 1"), std::string::npos) << m;
  EXPECT_NE(m.find("tether_requests_total{transport=\"http\",endpoint=\"/act\",status=\"500\"} 1"), std::string::npos) << m;
}

TEST(ActPipeline, ChecksTheKeyTheTransportPresents) {
  ServerOptions o;
  o.api_key = "s3cret";
  Fixture f(o);
  RequestContext ctx;
  ActResponse r = f.run(act_body(0), ctx);
  EXPECT_EQ(r.status, 401);
  EXPECT_EQ(code_of(r), "unauthorized");
  ctx.api_key = "wrong";
  EXPECT_EQ(f.run(act_body(0), ctx).status, 401);
  ctx.api_key = "s3cret";
  EXPECT_EQ(f.run(act_body(0), ctx).status, 200);
}

TEST(ActPipeline, RefusesBeforeTheModelIsReady) {
  Fixture f({}, /*load=*/false);
  const ActResponse r = f.run(act_body(0));
  EXPECT_EQ(r.status, 503);
  EXPECT_EQ(code_of(r), "not_ready");
  EXPECT_EQ(r.retry_after_s, 1);
}

TEST(ActPipeline, EnforcesTheBodyLimitForTransportsThatHandOverWholeMessages) {
  ServerOptions o;
  o.max_body_bytes = 64;
  Fixture f(o);
  const ActResponse r = f.run(act_body(0));
  EXPECT_EQ(r.status, 413);
  EXPECT_EQ(code_of(r), "body_too_large");
}

TEST(ActPipeline, AForwardedRequestIsNeverForwardedAgain) {
  ServerOptions o;
  o.wedges.cloud_fallback = "http://127.0.0.1:1";  // nothing listens: the attempt fails fast
  o.wedges.fallback_timeout_ms = 500;
  Fixture f(o);
  *f.fail = true;
  ActResponse r = f.run(act_body(0));
  EXPECT_EQ(r.status, 500);
  EXPECT_NE(r.body["error"]["message"].get<std::string>().find("fallback unreachable"), std::string::npos)
      << r.body.dump();
  RequestContext forwarded;
  forwarded.from_fallback = true;
  r = f.run(act_body(0), forwarded);
  EXPECT_EQ(r.status, 500);
  EXPECT_EQ(r.body["error"]["message"].get<std::string>().find("fallback"), std::string::npos) << r.body.dump();
  const std::string m = f.metrics.render();
  EXPECT_NE(m.find("tether_fallback_total{outcome=\"failure\"} 1\n"), std::string::npos) << m;
}

TEST(ActPipeline, RecordsATraceLineForSuccessAndFailure) {
  const auto dir = tether::testing::scratch_dir() / "pipeline_trace";
  std::filesystem::remove_all(dir);
  ServerOptions o;
  runtime::TraceOptions t;
  t.dir = dir.string();
  t.fsync = runtime::TraceOptions::Fsync::every_line;
  o.wedges.record = t;
  {
    Fixture f(o);
    ASSERT_EQ(f.run(act_body(1)).status, 200);
    ASSERT_EQ(f.run("{}").status, 400);
  }
  const std::vector<Json> lines = serve::testing::read_trace_lines(dir);
  ASSERT_EQ(lines.size(), 2u);
  EXPECT_EQ(lines[0]["status"], "success");
  EXPECT_EQ(lines[0]["model"], "fake-model");
  EXPECT_EQ(lines[0]["request_id"], "req-1");
  EXPECT_EQ(lines[1]["status"], "failed");
  EXPECT_EQ(lines[1]["http_status"], 400);
  std::filesystem::remove_all(dir);
}

// Two embodiments of one model: "arm" (the fake engine: state 2) and "humanoid" (state 3, chunk offset by 1000).
Engine embodiment_engine(const std::string& tag) {
  Engine e = fake_engine(std::make_shared<std::atomic<bool>>(false));
  e.spec.embodiment = tag;
  if (tag == "humanoid") {
    e.spec.state_dim = 3;
    auto base = e.predict;
    e.predict = [base](const std::vector<policy::Observation>& batch) {
      policy::Prediction p = base(batch);
      for (auto& c : p.items)
        for (float& v : c.actions) v += 1000;
      return p;
    };
  }
  return e;
}

struct TwoEmbodiments {
  explicit TwoEmbodiments(ServerOptions o = {})
      : opts(std::move(o)),
        metrics("test", ""),
        hosts({{"arm", [] { return embodiment_engine("arm"); }}, {"humanoid", [] { return embodiment_engine("humanoid"); }}},
              opts.batch, opts.wedges, metrics),
        pipeline(opts, hosts, metrics) {
    EXPECT_TRUE(hosts.load());
  }
  ~TwoEmbodiments() { hosts.stop(); }

  ActResponse run(const Json& body) { return run_body(pipeline, body.dump()); }

  ServerOptions opts;
  Metrics metrics;
  ModelHosts hosts;
  ActPipeline pipeline;
};

Json act_json(std::vector<float> state, std::optional<std::string> tag) {
  Json j = Json::parse(act_body(state[0]));
  j["state"] = state;
  if (tag) j["embodiment_tag"] = *tag;
  return j;
}

TEST(ModelHosts, RoutesEachRequestToItsEmbodiment) {
  TwoEmbodiments f;
  EXPECT_EQ(f.hosts.embodiments(), (std::vector<std::string>{"arm", "humanoid"}));
  const ActResponse arm = f.run(act_json({1, 0}, "arm"));
  ASSERT_EQ(arm.status, 200) << arm.body.dump();
  EXPECT_EQ(arm.body["actions"][0][0].get<float>(), 1.0f);
  const ActResponse humanoid = f.run(act_json({1, 0, 0}, "humanoid"));
  ASSERT_EQ(humanoid.status, 200) << humanoid.body.dump();
  EXPECT_EQ(humanoid.body["actions"][0][0].get<float>(), 1001.0f);
  // No tag: the first one.
  EXPECT_EQ(f.run(act_json({2, 0}, std::nullopt)).body["actions"][0][0].get<float>(), 2.0f);
  // Decoded against the embodiment named: the arm's state is not the humanoid's.
  const ActResponse wrong = f.run(act_json({1, 0}, "humanoid"));
  EXPECT_EQ(wrong.status, 400);
  EXPECT_EQ(code_of(wrong), "invalid_state");
}

TEST(ModelHosts, AnUnknownTagIsA400ListingTheServedOnes) {
  TwoEmbodiments f;
  const ActResponse r = f.run(act_json({1, 0}, "quadruped"));
  EXPECT_EQ(r.status, 400);
  EXPECT_EQ(code_of(r), "unknown_embodiment");
  EXPECT_NE(r.body["error"]["message"].get<std::string>().find("arm, humanoid"), std::string::npos);
  Json bad = act_json({1, 0}, std::nullopt);
  bad["embodiment_tag"] = 3;
  const ActResponse typed = f.run(bad);
  EXPECT_EQ(typed.status, 400);
  EXPECT_EQ(code_of(typed), "invalid_field");
  EXPECT_EQ(f.run(act_json({1, 0}, "arm")).status, 200);
}

TEST(ModelHosts, ASingleModelWithoutTagsRefusesANamedOne) {
  Fixture f;
  Json j = Json::parse(act_body(1));
  j["embodiment_tag"] = "arm";
  const ActResponse r = f.run(j.dump());
  EXPECT_EQ(r.status, 400);
  EXPECT_EQ(code_of(r), "unknown_embodiment");
  EXPECT_NE(r.body["error"]["message"].get<std::string>().find("no embodiment tags"), std::string::npos);
}

TEST(ModelHosts, HealthIsTheLeastReadyHostsAndTagsMustBeDistinct) {
  Metrics metrics("test", "");
  ModelHosts hosts({{"arm", [] { return embodiment_engine("arm"); }},
                    {"humanoid", []() -> Engine { throw Error(ErrorCode::not_found, "no such embodiment"); }}},
                   {}, {}, metrics);
  EXPECT_EQ(hosts.health(), HealthState::loading);
  EXPECT_FALSE(hosts.load());
  EXPECT_EQ(hosts.health(), HealthState::failed);
  EXPECT_TRUE(hosts.load_error());
  hosts.stop();
  EXPECT_THROW(ModelHosts({{"arm", [] { return embodiment_engine("arm"); }}, {"arm", [] { return embodiment_engine("arm"); }}},
                          {}, {}, metrics),
               Error);
  EXPECT_THROW(ModelHosts({{"", [] { return embodiment_engine("arm"); }}, {"humanoid", [] { return embodiment_engine("humanoid"); }}},
                          {}, {}, metrics),
               Error);
}

TEST(ModelHosts, EachEmbodimentRecordsItsOwnTraceChain) {
  const std::filesystem::path dir = tether::testing::scratch_dir() / "embodiment_traces";
  std::filesystem::remove_all(dir);
  ServerOptions o;
  o.wedges.record = runtime::TraceOptions{dir.string()};
  TwoEmbodiments f(o);
  ASSERT_EQ(f.run(act_json({1, 0}, "arm")).status, 200);
  ASSERT_EQ(f.run(act_json({1, 0, 0}, "humanoid")).status, 200);
  ASSERT_EQ(f.run(act_json({1, 0}, "humanoid")).status, 400);
  f.hosts.stop();
  for (const char* tag : {"arm", "humanoid"}) {
    const auto lines = serve::testing::read_trace_lines(dir / tag);
    ASSERT_FALSE(lines.empty()) << tag;
    for (const auto& l : lines) EXPECT_EQ(l["embodiment"], tag);
    EXPECT_EQ(lines.front()["seq"], 1);
  }
  EXPECT_EQ(serve::testing::read_trace_lines(dir / "humanoid").size(), 2u);
}

TEST(ActPipeline, RtcIsRefusedForActionsRelativeToTheStateUnlessReanchored) {
  ServerOptions o;
  o.wedges.sampler.rtc = true;
  Metrics metrics("test", "");
  ModelHosts hosts({{"", [] {
                       Engine e = embodiment_engine("arm");
                       e.spec.relative_actions = true;
                       return e;
                     }}},
                   o.batch, o.wedges, metrics);
  ASSERT_TRUE(hosts.load());
  ActPipeline pipeline(o, hosts, metrics);
  Json body = Json::parse(act_body(1));
  body["rtc"] = {{"prev_actions", {{1, 2}, {3, 4}}}, {"inference_delay", 1}};
  const ActResponse r = run_body(pipeline, body.dump());
  EXPECT_EQ(r.status, 400);
  EXPECT_EQ(code_of(r), "invalid_field");
  EXPECT_NE(r.body["error"]["message"].get<std::string>().find("relative to the state"), std::string::npos);
  hosts.stop();

  // pi0 / pi0.5 (lerobot's use_relative_actions): the policy re-anchors the leftover on the request's state instead.
  ModelHosts reanchoring({{"", [] {
                            Engine e = embodiment_engine("arm");
                            e.spec.relative_actions = e.spec.relative_rtc_reanchored = true;
                            return e;
                          }}},
                         o.batch, o.wedges, metrics);
  ASSERT_TRUE(reanchoring.load());
  ActPipeline accepting(o, reanchoring, metrics);
  const ActResponse ok = run_body(accepting, body.dump());
  EXPECT_EQ(ok.status, 200) << ok.body.dump();
  reanchoring.stop();
}
