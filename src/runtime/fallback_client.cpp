// Building the fallback request and judging its reply; the transfer itself is hub::HttpClient's.
#include "runtime/fallback_client.h"

#include "core/json_util.h"

namespace tether::runtime {

FallbackClient::FallbackClient(std::string url, int timeout_ms, std::string api_key)
    : act_url_(std::move(url)), api_key_(std::move(api_key)), timeout_ms_(timeout_ms) {
  if (!act_url_.empty() && act_url_.back() == '/') act_url_.pop_back();
  act_url_ += "/act";
}

hub::HttpRequest FallbackClient::request_for(const std::string& body, const std::string& request_id) const {
  hub::HttpRequest r;
  r.method = "POST";
  r.url = act_url_;
  r.body = body;
  r.timeout_ms = timeout_ms_;
  r.headers = {"Content-Type: application/json", "X-Tether-Request-ID: " + request_id,
               std::string(kFallbackMarkerHeader) + ": 1"};
  if (!api_key_.empty()) r.headers.push_back("Authorization: Bearer " + api_key_);
  return r;
}

FallbackReply FallbackClient::read_reply(const hub::HttpResult& res, int64_t dim) {
  FallbackReply reply;
  auto fail = [&](std::string why) {
    reply.error = std::move(why);
    return reply;
  };
  if (res.failure != hub::TransportFailure::none) return fail("fallback unreachable: " + res.error);
  if (res.response.status != 200) return fail("fallback answered HTTP " + std::to_string(res.response.status));
  const Json j = Json::parse(res.response.body, nullptr, false);
  if (j.is_discarded() || !j.is_object() || !j.contains("actions") || !j["actions"].is_array() || j["actions"].empty())
    return fail("fallback answered without an actions array");
  std::vector<float> actions;
  for (const auto& row : j["actions"]) {
    if (!row.is_array() || int64_t(row.size()) != dim)
      return fail("fallback actions do not have " + std::to_string(dim) + " values per row");
    for (const auto& v : row) {
      if (!v.is_number()) return fail("fallback actions hold a non-number");
      actions.push_back(float(v.get<double>()));
    }
  }
  reply.rows = int64_t(j["actions"].size());
  reply.actions = std::move(actions);
  return reply;
}

FallbackReply FallbackClient::call(const std::string& body, const std::string& request_id, int64_t action_dim) const {
  return read_reply(hub::HttpClient().perform(request_for(body, request_id)), action_dim);
}

}  // namespace tether::runtime
