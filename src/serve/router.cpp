// The endpoints other than /act's pipeline, and the per-request catch-all that answers 500.
#include "serve/router.h"

#include "serve/auth.h"
#include "serve/http_error.h"
#include "serve/wedge_metrics.h"
#include "serve/zmq_protocol.h"

namespace tether::serve {

namespace http = boost::beast::http;

Router::Router(const ServerOptions& options, ModelHost& host, Metrics& metrics, ActPipeline& pipeline)
    : opts_(options), host_(host), metrics_(metrics), pipeline_(pipeline), kserve_(options, host, metrics, pipeline) {}

Json Router::health_json(HealthState s) const {
  const bool ok = s == HealthState::ready;
  Json h = {{"status", ok ? "ok" : "unavailable"},
            {"state", health_state_name(s)},
            {"model_hash", host_.loaded() ? Json(host_.engine().model_hash) : Json(nullptr)}};
  const auto& b = host_.wedges().breaker();
  if (b.enabled()) {
    h["circuit"] = {{"state", runtime::circuit_state_name(b.state())},
                    {"consecutive_failures", b.consecutive_failures()},
                    {"times_opened", b.times_opened()},
                    {"retry_after_s", b.retry_after_s()}};
  }
  return h;
}

Json Router::config_json() const {
  const Engine& engine = host_.engine();
  const auto& s = engine.spec;
  return {{"family", s.family},
          {"cameras", s.cameras},
          {"missing_camera_rule", s.missing_camera_rule},
          {"stages", s.stages},
          {"state_dim", s.state_dim},
          {"action_dim", host_.wedges().action_dim()},  // what /act answers (an embodiment may cut a padded output)
          {"chunk_size", s.chunk_size},
          {"num_steps", s.num_steps},
          {"normalization", engine.normalization},
          {"weights_dtype", s.weights_dtype},
          {"model_hash", engine.model_hash},
          {"inference_mode", inference_mode_json(engine)},
          {"load_warnings", engine.load_warnings},
          {"wedges", host_.wedges().config_json()},
          {"limits",
           {{"max_batch", opts_.batch.max_batch},
            {"batch_timeout_ms", opts_.batch.batch_timeout_ms},
            {"max_queue", opts_.batch.max_queue},
            {"max_body_bytes", opts_.max_body_bytes},
            {"max_header_bytes", opts_.max_header_bytes},
            {"read_timeout_ms", opts_.read_timeout_ms},
            {"write_timeout_ms", opts_.write_timeout_ms},
            {"request_timeout_ms", opts_.request_timeout_ms},
            {"shutdown_timeout_ms", opts_.shutdown_timeout_ms}}}};
}

boost::asio::awaitable<HttpResponse> Router::route(const HttpRequest& req, const std::string& request_id) {
  const std::string path(req.target().substr(0, req.target().find('?')));
  const bool is_get = req.method() == http::verb::get;
  auto require_method = [&](bool ok, const char* allow) {
    if (!ok) throw HttpError(405, "method_not_allowed", path + " accepts " + allow + " only");
  };
  if (path == "/health") {
    require_method(is_get, "GET");
    const HealthState s = host_.health();
    HttpResponse res = json_response(req, s == HealthState::ready ? 200 : 503, health_json(s), request_id);
    if (s == HealthState::circuit_open)
      res.set(http::field::retry_after, std::to_string(std::max(1, host_.wedges().breaker().retry_after_s())));
    co_return res;
  }
  if (path == "/ready") {
    require_method(is_get, "GET");
    const bool ready = host_.health() == HealthState::ready;
    co_return json_response(req, ready ? 200 : 503, {{"ready", ready}}, request_id);
  }
  if (path == "/live") {
    require_method(is_get, "GET");
    co_return json_response(req, 200, {{"live", true}}, request_id);
  }
  if (path == "/config") {
    require_method(is_get, "GET");
    check_api_key(presented_api_key(req), opts_.api_key);
    if (!host_.loaded()) throw HttpError(503, "not_ready", "the model is still loading");
    co_return json_response(req, 200, config_json(), request_id);
  }
  if (path == "/metrics") {
    require_method(is_get, "GET");
    metrics_.set_queue_depth(host_.loaded() ? host_.batcher().queue_depth() : 0);
    refresh_wedge_gauges(metrics_, host_.wedges());
    metrics_.set_model_ready(host_.health() == HealthState::ready);
    co_return make_response(req, http::status::ok, metrics_.render(), request_id,
                            "text/plain; version=0.0.4; charset=utf-8");
  }
  throw HttpError(404, "not_found", "no endpoint " + path + " (try /act, /health, /ready, /live, /config, /metrics)");
}

boost::asio::awaitable<HttpResponse> Router::handle(const HttpRequest& req,
                                                    std::chrono::steady_clock::time_point received) {
  const std::string request_id = request_id_of(req);
  const std::string path(req.target().substr(0, req.target().find('?')));
  // A POST to /act goes to the pipeline, which counts its own answers (as it does for every transport).
  if (path == "/act" && req.method() == http::verb::post) {
    const RequestContext ctx = act_context(req, request_id, received);
    const std::string_view body = req.body();
    if (has_msgpack_body(req)) {
      // The binary body: raw image bytes without base64 (docs/serve-api.md#msgpack-bodies).
      const ActInput input{body.size(),
                           [body](const models::ModelSpec& spec) { return zmqp::decode_http_body(body, spec); },
                           [](const ActRequest& r) { return act_request_json(r); }};
      const ActResponse act = co_await pipeline_.run(input, ctx);
      co_return act_response(req, act, request_id, accepts_msgpack(req));
    }
    const ActResponse act = co_await pipeline_.run(body, ctx);
    co_return act_response(req, act, request_id, accepts_msgpack(req));
  }
  if (is_kserve_path(path)) co_return co_await kserve_.handle(req, request_id, received);
  int status = 500, retry_after_s = 1;
  std::string code = "internal_error", message;
  try {
    if (path == "/act") throw HttpError(405, "method_not_allowed", path + " accepts POST only");
    HttpResponse res = co_await route(req, request_id);
    metrics_.count_request(endpoint_label(req.target()), res.result_int());
    co_return res;
  } catch (const HttpError& e) {
    status = e.status();
    code = e.code();
    message = e.what();
    retry_after_s = e.retry_after_s();
  } catch (const std::exception& e) {
    message = std::string("internal error: ") + e.what();
  } catch (...) {
    message = "internal error";
  }
  metrics_.count_request(endpoint_label(req.target()), status);
  co_return error_response(req, status, code, message, request_id, retry_after_s);
}

}  // namespace tether::serve
