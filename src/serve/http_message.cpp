// Reading request headers and building the server's HTTP responses.
#include "serve/http_message.h"

#include <algorithm>
#include <cctype>

#include "runtime/fallback_client.h"
#include "serve/http_error.h"
#include "serve/request_id.h"
#include "serve/zmq_protocol.h"

namespace tether::serve {

namespace http = boost::beast::http;

namespace {

std::string dump(const Json& body) { return body.dump(-1, ' ', false, Json::error_handler_t::replace); }

const char* kKnownPaths[] = {"/act", "/health", "/ready", "/live", "/config", "/metrics"};

// A media type without its parameters, trimmed and lower-cased ("Application/MsgPack; q=1" -> "application/msgpack").
std::string media_type(std::string_view v) {
  v = v.substr(0, v.find(';'));
  while (!v.empty() && (v.front() == ' ' || v.front() == '\t')) v.remove_prefix(1);
  while (!v.empty() && (v.back() == ' ' || v.back() == '\t')) v.remove_suffix(1);
  std::string out(v);
  for (char& c : out) c = char(std::tolower(static_cast<unsigned char>(c)));
  return out;
}

bool is_msgpack_type(std::string_view v) {
  const std::string t = media_type(v);
  return t == "application/msgpack" || t == "application/x-msgpack";
}

}  // namespace

std::string header(const HttpRequest& req, std::string_view name) {
  auto it = req.find(name);
  return it == req.end() ? std::string() : std::string(it->value());
}

std::string request_id_of(const HttpRequest& req) {
  return request_id_or_new({header(req, "X-Tether-Request-ID"), header(req, "X-Request-ID")});
}

std::string presented_api_key(const HttpRequest& req) {
  std::string given = header(req, "X-Tether-Key");
  if (given.empty()) {
    const std::string auth = header(req, "Authorization");
    if (auth.size() > 7 && (auth.compare(0, 7, "Bearer ") == 0 || auth.compare(0, 7, "bearer ") == 0))
      given = auth.substr(7);
  }
  return given;
}

RequestContext act_context(const HttpRequest& req, std::string request_id,
                           std::chrono::steady_clock::time_point received) {
  RequestContext ctx;
  ctx.request_id = std::move(request_id);
  ctx.api_key = presented_api_key(req);
  ctx.received = received;
  ctx.from_fallback = !header(req, runtime::kFallbackMarkerHeader).empty();
  return ctx;
}

std::string endpoint_label(std::string_view target) {
  const std::string_view path = target.substr(0, target.find('?'));
  for (const char* p : kKnownPaths)
    if (path == p) return p;
  return "other";
}

HttpResponse make_response(const HttpRequest& req, http::status status, const std::string& body,
                           const std::string& request_id, const char* content_type) {
  HttpResponse res{status, req.version()};
  res.set(http::field::server, "tether/" TETHER_VERSION);
  res.set(http::field::content_type, content_type);
  res.set("X-Tether-Request-ID", request_id);
  res.body() = body;
  res.prepare_payload();
  return res;
}

HttpResponse error_response(const HttpRequest& req, int status, const std::string& code, const std::string& message,
                            const std::string& request_id, int retry_after_s) {
  HttpResponse res = make_response(req, http::status(status), dump(error_body(code, message)), request_id);
  if (status == 503) res.set(http::field::retry_after, std::to_string(retry_after_s));
  return res;
}

HttpResponse json_response(const HttpRequest& req, int status, const Json& body, const std::string& request_id) {
  HttpResponse res = make_response(req, http::status(status), dump(body), request_id);
  if (status == 503) res.set(http::field::retry_after, "1");
  return res;
}

bool has_msgpack_body(const HttpRequest& req) { return is_msgpack_type(header(req, "Content-Type")); }

bool accepts_msgpack(const HttpRequest& req) {
  const std::string accept = header(req, "Accept");
  for (std::size_t start = 0; start <= accept.size();) {
    const std::size_t comma = std::min(accept.find(',', start), accept.size());
    if (is_msgpack_type(std::string_view(accept).substr(start, comma - start))) return true;
    start = comma + 1;
  }
  return false;
}

HttpResponse act_response(const HttpRequest& req, const ActResponse& act, const std::string& request_id,
                          bool msgpack) {
  HttpResponse res = msgpack ? make_response(req, http::status(act.status), zmqp::encode_body(act.body), request_id,
                                             "application/msgpack")
                             : make_response(req, http::status(act.status), dump(act.body), request_id);
  if (act.status == 503) res.set(http::field::retry_after, std::to_string(act.retry_after_s));
  return res;
}

std::string query_parameter(std::string_view target, std::string_view key) {
  const auto q = target.find('?');
  if (q == std::string_view::npos) return "";
  std::string_view rest = target.substr(q + 1);
  while (!rest.empty()) {
    const auto amp = rest.find('&');
    const std::string_view pair = rest.substr(0, amp);
    if (pair.size() > key.size() && pair.substr(0, key.size()) == key && pair[key.size()] == '=')
      return std::string(pair.substr(key.size() + 1));
    if (amp == std::string_view::npos) break;
    rest = rest.substr(amp + 1);
  }
  return "";
}

}  // namespace tether::serve
