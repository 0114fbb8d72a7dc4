// The cloud fallback's client: forwards an /act body to another Tether server and checks the actions it answers.
// Blocking (libcurl): callers run it off their I/O threads.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "hub/http.h"

namespace tether::runtime {

// What the fallback gave: actions (rows x action_dim, row-major) or why not.
struct FallbackReply {
  std::optional<std::vector<float>> actions;
  int64_t rows = 0;
  std::string error;  // set when `actions` is absent, e.g. "fallback answered HTTP 503"
};

// Header that marks a request as forwarded by a fallback client: its receiver answers locally and never forwards
// it again (two servers naming each other cannot bounce a request forever).
inline constexpr const char* kFallbackMarkerHeader = "X-Tether-Fallback";

class FallbackClient {
 public:
  // `url`: the other server's base URL (its /act is called); `api_key`: sent as a bearer token when not empty.
  FallbackClient(std::string url, int timeout_ms, std::string api_key);

  // POSTs `body` to <url>/act carrying `request_id`; `action_dim` values per row are expected back.
  FallbackReply call(const std::string& body, const std::string& request_id, int64_t action_dim) const;

  // The request call() sends (exposed for tests).
  hub::HttpRequest request_for(const std::string& body, const std::string& request_id) const;
  // Judges the other server's answer (exposed for tests: no network needed).
  static FallbackReply read_reply(const hub::HttpResult& result, int64_t action_dim);

 private:
  std::string act_url_, api_key_;
  int timeout_ms_;
};

}  // namespace tether::runtime
