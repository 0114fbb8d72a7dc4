// The endpoints other than /act's pipeline, and the per-request catch-all that answers 500.
#include "serve/router.h"

#include "serve/auth.h"
#include "serve/http_error.h"
#include "serve/wedge_metrics.h"
#include "serve/zmq_protocol.h"

namespace tether::serve {

namespace http = boost::beast::http;

Router::Router(const ServerOptions& options, ModelHosts& hosts, Metrics& metrics, ActPipeline& pipeline)
    : opts_(options), hosts_(hosts), metrics_(metrics), pipeline_(pipeline), kserve_(options, hosts, metrics, pipeline) {}

namespace {

Json circuit_json(const runtime::CircuitBreaker& b) {
  return {{"state", runtime::circuit_state_name(b.state())},
          {"consecutive_failures", b.consecutive_failures()},
          {"times_opened", b.times_opened()},
          {"retry_after_s", b.retry_after_s()}};
}

}  // namespace

Json Router::health_json(HealthState s) const {
  const bool ok = s == HealthState::ready;
  const ModelHost& primary = hosts_.primary();
  Json h = {{"status", ok ? "ok" : "unavailable"},
            {"state", health_state_name(s)},
            {"model_hash", primary.loaded() ? Json(primary.engine().model_hash) : Json(nullptr)}};
  if (primary.wedges().breaker().enabled()) h["circuit"] = circuit_json(primary.wedges().breaker());
  if (hosts_.size() > 1) {  // each embodiment's own state (its batcher and circuit are its own)
    Json each = Json::object();
    for (std::size_t i = 0; i < hosts_.size(); ++i) {
      const ModelHost& host = hosts_[i];
      Json e = {{"state", health_state_name(host.health())}};
      if (host.wedges().breaker().enabled()) e["circuit"] = circuit_json(host.wedges().breaker());
      each[host.embodiment()] = std::move(e);
    }
    h["embodiments"] = std::move(each);
  }
  return h;
}

Json Router::config_json(const ModelHost& host) const {
  const Engine& engine = host.engine();
  const auto& s = engine.spec;
  return {{"family", s.family},
          {"embodiment", s.embodiment.empty() ? Json(nullptr) : Json(s.embodiment)},
          {"embodiments", hosts_.embodiments()},
          {"cameras", s.cameras},
          {"missing_camera_rule", s.missing_camera_rule},
          {"stages", s.stages},
          {"state_dim", s.state_dim},
          {"action_dim", host.wedges().action_dim()},  // what /act answers (an embodiment may cut a padded output)
          {"state_groups", models::groups_json(models::state_groups(s))},
          {"action_groups", models::groups_json(models::answered_action_groups(s, host.wedges().action_dim()))},
          {"modality_config", s.modality_config},
          {"chunk_size", s.chunk_size},
          {"num_steps", s.num_steps},
          {"normalization", engine.normalization},
          {"weights_dtype", s.weights_dtype},
          {"model_hash", engine.model_hash},
          {"inference_mode", inference_mode_json(engine)},
          {"load_warnings", engine.load_warnings},
          {"wedges", host.wedges().config_json()},
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
    const HealthState s = hosts_.health();
    HttpResponse res = json_response(req, s == HealthState::ready ? 200 : 503, health_json(s), request_id);
    if (s == HealthState::circuit_open) {
      int retry = 1;
      for (std::size_t i = 0; i < hosts_.size(); ++i) retry = std::max(retry, hosts_[i].wedges().breaker().retry_after_s());
      res.set(http::field::retry_after, std::to_string(retry));
    }
    co_return res;
  }
  if (path == "/ready") {
    require_method(is_get, "GET");
    const bool ready = hosts_.health() == HealthState::ready;
    co_return json_response(req, ready ? 200 : 503, {{"ready", ready}}, request_id);
  }
  if (path == "/live") {
    require_method(is_get, "GET");
    co_return json_response(req, 200, {{"live", true}}, request_id);
  }
  if (path == "/config") {
    require_method(is_get, "GET");
    check_api_key(presented_api_key(req), opts_.api_key);
    // One embodiment's configuration: ?embodiment_tag=<tag>, else the default's.
    const ModelHost& host = hosts_.route(query_parameter(req.target(), "embodiment_tag"));
    if (!host.loaded()) throw HttpError(503, "not_ready", "the model is still loading");
    co_return json_response(req, 200, config_json(host), request_id);
  }
  if (path == "/metrics") {
    require_method(is_get, "GET");
    // Each embodiment's wedge gauges (labelled by embodiment when there are several); the queue depth and
    // readiness of them all.
    int depth = 0;
    for (std::size_t i = 0; i < hosts_.size(); ++i) {
      refresh_wedge_gauges(metrics_, hosts_[i].wedges(), hosts_[i].metric_labels());
      if (hosts_[i].loaded()) depth += hosts_[i].batcher().queue_depth();
    }
    metrics_.set_queue_depth(depth);
    metrics_.set_model_ready(hosts_.health() == HealthState::ready);
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
                           [](const ActRequest& r) { return act_request_json(r); },
                           [body] { return zmqp::http_body_embodiment(body); }};
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
