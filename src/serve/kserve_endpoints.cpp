// The /v2 endpoints: path and method, the model's name and version, the health and metadata answers, and an infer
// request's items through the ActPipeline, joined back into one v2 response (JSON or binary tensor data).
#include "serve/kserve_endpoints.h"

#include <boost/asio/co_spawn.hpp>
#include <boost/asio/redirect_error.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/asio/this_coro.hpp>
#include <boost/asio/use_awaitable.hpp>
#include <vector>

#include "serve/auth.h"
#include "serve/http_error.h"
#include "serve/kserve_protocol.h"

namespace tether::serve {

namespace net = boost::asio;
namespace http = boost::beast::http;

namespace {

constexpr const char* kTransport = "kserve";

enum class Kind { server_metadata, live, ready, model_metadata, model_ready, infer, unknown };

struct V2Path {
  Kind kind = Kind::unknown;
  std::string model, version;  // version: "" when the path names none
};

std::string percent_decode(std::string_view s) {
  std::string out;
  for (std::size_t i = 0; i < s.size(); ++i) {
    const auto hex = [](char c) {
      return c >= '0' && c <= '9' ? c - '0' : c >= 'a' && c <= 'f' ? c - 'a' + 10 : c >= 'A' && c <= 'F' ? c - 'A' + 10 : -1;
    };
    if (s[i] == '%' && i + 2 < s.size() && hex(s[i + 1]) >= 0 && hex(s[i + 2]) >= 0) {
      out.push_back(char(hex(s[i + 1]) * 16 + hex(s[i + 2])));
      i += 2;
    } else {
      out.push_back(s[i]);
    }
  }
  return out;
}

std::string path_of(std::string_view target) { return std::string(target.substr(0, target.find('?'))); }

V2Path parse_path(std::string_view target) {
  std::string path = path_of(target);
  while (path.size() > 3 && path.back() == '/') path.pop_back();  // "/v2/" is "/v2"
  std::vector<std::string> parts;
  for (std::size_t at = 1; at <= path.size();) {
    const std::size_t slash = std::min(path.find('/', at), path.size());
    parts.push_back(path.substr(at, slash - at));
    at = slash + 1;
  }
  V2Path p;
  if (parts.empty() || parts[0] != "v2") return p;
  const std::size_t n = parts.size();
  if (n == 1) p.kind = Kind::server_metadata;
  else if (n == 3 && parts[1] == "health" && parts[2] == "live") p.kind = Kind::live;
  else if (n == 3 && parts[1] == "health" && parts[2] == "ready") p.kind = Kind::ready;
  else if (n >= 3 && parts[1] == "models" && !parts[2].empty()) {
    p.model = percent_decode(parts[2]);
    std::size_t at = 3;
    if (n >= 5 && parts[3] == "versions") {
      p.version = percent_decode(parts[4]);
      at = 5;
    }
    if (n == at) p.kind = Kind::model_metadata;
    else if (n == at + 1 && parts[at] == "ready") p.kind = Kind::model_ready;
    else if (n == at + 1 && parts[at] == "infer") p.kind = Kind::infer;
  }
  return p;
}

std::string dump(const Json& j) { return j.dump(-1, ' ', false, Json::error_handler_t::replace); }

// The /act error body's message (every pipeline error has one).
std::string error_message(const Json& body) {
  const auto e = body.find("error");
  if (e != body.end() && e->is_object() && e->contains("message") && (*e)["message"].is_string())
    return (*e)["message"].get<std::string>();
  return "request failed";
}

}  // namespace

bool is_kserve_path(std::string_view target) {
  const std::string path = path_of(target);
  return path == "/v2" || path.rfind("/v2/", 0) == 0;
}

std::string kserve_endpoint_label(std::string_view target) {
  switch (parse_path(target).kind) {
    case Kind::server_metadata: return "/v2";
    case Kind::live: return "/v2/health/live";
    case Kind::ready: return "/v2/health/ready";
    case Kind::model_metadata: return "/v2/models/{name}";
    case Kind::model_ready: return "/v2/models/{name}/ready";
    case Kind::infer: return "/v2/models/{name}/infer";
    case Kind::unknown: break;
  }
  return "other";
}

HttpResponse kserve_error_response(const HttpRequest& req, int status, const std::string& message,
                                   const std::string& request_id, int retry_after_s) {
  HttpResponse res = make_response(req, http::status(status), dump(kserve::error_json(message)), request_id);
  if (status == 503) res.set(http::field::retry_after, std::to_string(std::max(1, retry_after_s)));
  return res;
}

// An infer request decoded, with what its items' pipeline requests need; items and contexts live here while the
// pipeline awaits them.
struct KServeEndpoints::Prepared {
  kserve::InferRequest request;
  std::vector<ActInput> inputs;
  std::vector<RequestContext> contexts;
};

KServeEndpoints::KServeEndpoints(const ServerOptions& options, ModelHosts& hosts, Metrics& metrics,
                                 ActPipeline& pipeline)
    : opts_(options), hosts_(hosts), metrics_(metrics), pipeline_(pipeline) {}

std::string KServeEndpoints::model_name() const {
  if (!opts_.model_name.empty()) return opts_.model_name;
  const ModelHost& host = hosts_.primary();
  return host.loaded() ? host.engine().model_name : std::string("model");
}

namespace {

void check_model(const V2Path& p, const std::string& served) {
  if (p.model != served)
    throw HttpError(404, "not_found", "unknown model '" + p.model + "' (this server serves '" + served + "')");
  if (!p.version.empty() && p.version != kserve::kModelVersion)
    throw HttpError(404, "not_found", "model '" + p.model + "' has no version '" + p.version + "' (it has version " +
                                          kserve::kModelVersion + ")");
}

void require_method(const HttpRequest& req, http::verb verb) {
  if (req.method() != verb)
    throw HttpError(405, "method_not_allowed",
                    path_of(req.target()) + " accepts " + std::string(http::to_string(verb)) + " only");
}

}  // namespace

HttpResponse KServeEndpoints::get(const HttpRequest& req, const std::string& request_id) {
  const V2Path p = parse_path(req.target());
  // Health answers are the status alone (200 true, 400 false) with an empty body, as the protocol says.
  const auto health = [&](bool ok) {
    HttpResponse res = make_response(req, ok ? http::status::ok : http::status::bad_request, "", request_id);
    return res;
  };
  switch (p.kind) {
    case Kind::server_metadata:
      require_method(req, http::verb::get);
      return json_response(req, 200, kserve::server_metadata(TETHER_VERSION), request_id);
    case Kind::live:
      require_method(req, http::verb::get);
      return health(true);
    case Kind::ready:
      require_method(req, http::verb::get);
      return health(hosts_.health() == HealthState::ready);
    case Kind::model_ready:
      require_method(req, http::verb::get);
      check_model(p, model_name());
      return health(hosts_.health() == HealthState::ready);
    case Kind::model_metadata: {
      require_method(req, http::verb::get);
      check_model(p, model_name());
      check_api_key(presented_api_key(req), opts_.api_key);
      const ModelHost& host = hosts_.primary();
      if (!host.loaded()) throw HttpError(503, "not_ready", "the model is still loading");
      Json metadata = kserve::model_metadata(model_name(), host.engine().spec, host.wedges().action_dim());
      // The default embodiment's tensors; an infer request picks another with parameters.embodiment_tag.
      if (hosts_.size() > 1 || !host.embodiment().empty())
        metadata["parameters"] = {{"embodiment_tag", host.embodiment()}, {"embodiments", hosts_.embodiments()}};
      return json_response(req, 200, metadata, request_id);
    }
    case Kind::infer:
    case Kind::unknown: break;
  }
  throw HttpError(404, "not_found",
                  "no endpoint " + path_of(req.target()) +
                      " (the v2 protocol here: /v2, /v2/health/live, /v2/health/ready, /v2/models/" + model_name() +
                      "[/versions/1][/ready|/infer])");
}

void KServeEndpoints::prepare(const HttpRequest& req, const std::string& request_id,
                              std::chrono::steady_clock::time_point received, Prepared& prep) {
  const V2Path p = parse_path(req.target());
  require_method(req, http::verb::post);
  check_model(p, model_name());
  // The pipeline's own order: the key before anything about the body, then readiness, then the size.
  check_api_key(presented_api_key(req), opts_.api_key);
  if (!hosts_.primary().serving())
    throw HttpError(503, "not_ready",
                    std::string("the model is not ready (") + health_state_name(hosts_.primary().health()) + ")");
  if (req.body().size() > opts_.max_body_bytes)
    throw HttpError(413, "body_too_large",
                    "the request exceeds " + std::to_string(opts_.max_body_bytes) + " bytes (--max-body-bytes)");
  const RequestContext base = [&] {
    RequestContext c = act_context(req, request_id, received);
    c.transport = kTransport;
    c.endpoint = kserve_endpoint_label(req.target());
    return c;
  }();
  try {
    const std::string encoding = header(req, "Content-Encoding");
    if (!encoding.empty() && encoding != "identity")
      throw HttpError(400, "invalid_field",
                      "Content-Encoding '" + encoding + "' is not supported: send the body uncompressed");
    prep.request = kserve::decode_infer_request(
        req.body(), header(req, "Inference-Header-Content-Length"),
        [this](const std::string& embodiment) -> const models::ModelSpec& {
          const ModelHost& host = hosts_.route(embodiment);
          if (!host.serving())
            throw HttpError(503, "not_ready",
                            "embodiment '" + embodiment + "' is not ready (" + health_state_name(host.health()) + ")");
          return host.engine().spec;
        });
  } catch (...) {
    // Refused while decoding: one pipeline request that fails at its decoding step, so the refusal is counted and
    // traced as any transport's is.
    prep.inputs.push_back(refused_input(req.body().size(), std::current_exception()));
    prep.contexts.push_back(base);
    return;
  }
  const std::size_t n = prep.request.items.size();
  prep.contexts.assign(n, base);
  prep.inputs.reserve(n);
  for (std::size_t i = 0; i < n; ++i) {
    // Items of a batch each get their own id (their traces and their default seeds differ): "<id>.<item>".
    if (n > 1) prep.contexts[i].request_id = request_id + "." + std::to_string(i);
    ActRequest* item = &prep.request.items[i];
    prep.inputs.push_back(ActInput{req.body().size(), [item](const models::ModelSpec&) { return std::move(*item); },
                                   [](const ActRequest& r) { return act_request_json(r); },
                                   [tag = prep.request.embodiment] { return tag; }});
  }
}

net::awaitable<HttpResponse> KServeEndpoints::run_items(const HttpRequest& req, const std::string& request_id,
                                                        Prepared& p) {
  // The items run concurrently on this executor, so they reach the batcher together; a timer wakes this coroutine
  // when the last one has answered.
  struct Join {
    explicit Join(const net::any_io_executor& ex, std::size_t n) : timer(ex), left(n), answers(n) {}
    net::steady_timer timer;
    std::size_t left;
    std::vector<ActResponse> answers;
  };
  const auto ex = co_await net::this_coro::executor;
  const std::size_t n = p.inputs.size();
  auto join = std::make_shared<Join>(ex, n);
  for (std::size_t i = 0; i < n; ++i) {
    net::co_spawn(ex, pipeline_.run(p.inputs[i], p.contexts[i]), [join, i](std::exception_ptr e, ActResponse r) {
      // run never throws; an exception here is a bug, answered as one.
      join->answers[i] = e ? ActResponse{500, error_body("internal_error", "internal error"), 1} : std::move(r);
      if (--join->left == 0) join->timer.cancel();
    });
  }
  while (join->left > 0) {
    join->timer.expires_at(net::steady_timer::time_point::max());
    boost::system::error_code ec;
    co_await join->timer.async_wait(net::redirect_error(net::use_awaitable, ec));
  }
  // The first item that failed decides the answer (each item was counted by the pipeline).
  for (std::size_t i = 0; i < n; ++i) {
    const ActResponse& a = join->answers[i];
    if (a.ok()) continue;
    const std::string message = error_message(a.body);
    co_return kserve_error_response(req, a.status, n > 1 ? "item " + std::to_string(i) + ": " + message : message,
                                    request_id, a.retry_after_s);
  }
  std::vector<kserve::ItemAnswer> answers(n);
  try {
    for (std::size_t i = 0; i < n; ++i) {
      const Json& body = join->answers[i].body;
      auto& a = answers[i];
      a.rows = body.at("num_actions").get<int64_t>();
      a.dim = body.at("action_dim").get<int64_t>();
      a.action_source = body.value("action_source", std::string("model"));
      if (const auto latency = body.find("latency_ms"); latency != body.end() && latency->is_object()) {
        a.total_ms = latency->value("total", 0.0);
        a.predict_ms = latency->value("predict", 0.0);
      }
      a.actions.reserve(std::size_t(a.rows * a.dim));
      for (const auto& row : body.at("actions"))
        for (const auto& v : row) a.actions.push_back(v.get<float>());
    }
    const kserve::EncodedResponse enc = kserve::encode_infer_response(model_name(), p.request, answers);
    HttpResponse res = make_response(req, http::status::ok, enc.body, request_id,
                                     enc.header_length ? "application/octet-stream" : "application/json");
    if (enc.header_length) res.set("Inference-Header-Content-Length", std::to_string(*enc.header_length));
    co_return res;
  } catch (const HttpError& e) {
    metrics_.count_request(kserve_endpoint_label(req.target()), e.status(), kTransport);
    co_return kserve_error_response(req, e.status(), e.what(), request_id);
  } catch (const std::exception& e) {
    metrics_.count_request(kserve_endpoint_label(req.target()), 500, kTransport);
    co_return kserve_error_response(req, 500, std::string("internal error: ") + e.what(), request_id);
  }
}

net::awaitable<HttpResponse> KServeEndpoints::handle(const HttpRequest& req, const std::string& request_id,
                                                     std::chrono::steady_clock::time_point received) {
  const std::string label = kserve_endpoint_label(req.target());
  int status = 500, retry_after_s = 1;
  std::string message;
  std::unique_ptr<Prepared> prep;
  try {
    if (parse_path(req.target()).kind == Kind::infer) {
      auto p = std::make_unique<Prepared>();
      prepare(req, request_id, received, *p);
      prep = std::move(p);
    } else {
      HttpResponse res = get(req, request_id);
      metrics_.count_request(label, res.result_int(), kTransport);
      co_return res;
    }
  } catch (const HttpError& e) {
    status = e.status();
    message = e.what();
    retry_after_s = e.retry_after_s();
  } catch (const std::exception& e) {
    message = std::string("internal error: ") + e.what();
  } catch (...) {
    message = "internal error";
  }
  if (prep) co_return co_await run_items(req, request_id, *prep);
  metrics_.count_request(label, status, kTransport);
  co_return kserve_error_response(req, status, message, request_id, retry_after_s);
}

}  // namespace tether::serve
