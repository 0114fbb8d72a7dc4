// The HTTP side of a request and its answer: Beast message types, header lookups, the request id and API key a
// client sent, and the responses the server writes (JSON bodies, Retry-After on 503).
#pragma once

#include <boost/beast/http.hpp>
#include <string>
#include <string_view>

#include "core/json_util.h"
#include "serve/act_pipeline.h"

namespace tether::serve {

using HttpRequest = boost::beast::http::request<boost::beast::http::string_body>;
using HttpResponse = boost::beast::http::response<boost::beast::http::string_body>;

// The header's value, or "" when absent.
std::string header(const HttpRequest& req, std::string_view name);
// X-Tether-Request-ID, then X-Request-ID, when valid; else a fresh id.
std::string request_id_of(const HttpRequest& req);
// The key in X-Tether-Key, else in "Authorization: Bearer <key>"; "" when neither is there.
std::string presented_api_key(const HttpRequest& req);
// What the /act pipeline needs to know about an HTTP request.
RequestContext act_context(const HttpRequest& req, std::string request_id,
                           std::chrono::steady_clock::time_point received);

// The endpoint label of tether_requests_total: a known path, or "other".
std::string endpoint_label(std::string_view target);

HttpResponse make_response(const HttpRequest& req, boost::beast::http::status status, const std::string& body,
                           const std::string& request_id, const char* content_type = "application/json");
// {"error": {...}}; a 503 carries Retry-After: `retry_after_s`.
HttpResponse error_response(const HttpRequest& req, int status, const std::string& code, const std::string& message,
                            const std::string& request_id, int retry_after_s = 1);
// A JSON body; a 503 carries Retry-After: 1.
HttpResponse json_response(const HttpRequest& req, int status, const Json& body, const std::string& request_id);
// Whether the request's Content-Type is msgpack (application/msgpack, or the older application/x-msgpack).
bool has_msgpack_body(const HttpRequest& req);
// Whether the request's Accept header lists msgpack: its /act answer is then a msgpack map.
bool accepts_msgpack(const HttpRequest& req);

// The pipeline's answer as HTTP: JSON, or with `msgpack` the same map as msgpack (actions as float32).
HttpResponse act_response(const HttpRequest& req, const ActResponse& act, const std::string& request_id,
                          bool msgpack = false);

// The value of `key` in a request target's query string ("/config?embodiment_tag=x" -> "x"), as written (no
// percent-decoding: the values it is used for are plain identifiers); empty when absent.
std::string query_parameter(std::string_view target, std::string_view key);

}  // namespace tether::serve
