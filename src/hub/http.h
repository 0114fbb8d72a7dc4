// A small blocking HTTP client over libcurl for the hub (and the server's cloud fallback): no automatic redirects (the caller decides
// where credentials may go), headers kept verbatim, bodies either buffered or streamed to a sink.
#pragma once

#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

namespace tether::hub {

struct HttpResponse {
  long status = 0;
  std::vector<std::pair<std::string, std::string>> headers;  // of the last response (after any 1xx)
  std::string body;                                          // only when no sink was given

  // Case-insensitive lookup; the last occurrence wins.
  std::optional<std::string> header(std::string_view name) const;
  bool is_redirect() const {
    return status >= 300 && status < 400 && header("Location").has_value();
  }
};

// Why a request produced no complete response.
enum class TransportFailure {
  none,
  connect,  // DNS or TCP/TLS connect failed: nothing was exchanged
  timeout,
  broken,   // the connection dropped or the transfer ended short
  aborted,  // the sink asked to stop
  other,
};

struct HttpResult {
  HttpResponse response;
  TransportFailure failure = TransportFailure::none;
  std::string error;  // curl's description when failure != none
};

struct HttpRequest {
  std::string method = "GET";  // GET, HEAD or POST (with `body`)
  std::string url;
  std::vector<std::string> headers;  // "Name: value"
  long connect_timeout_s = 10;
  long timeout_s = 0;        // whole request; 0 = unlimited (downloads), used for metadata calls
  long timeout_ms = 0;       // whole request in milliseconds, when set (overrides timeout_s and connect_timeout_s)
  std::string body;          // POST only
  long stall_timeout_s = 0;  // abort when under 1 byte/s for this long; 0 = never
  // Receives the body as it arrives; the response's status and headers are already filled in.
  // Returning false aborts the transfer.
  std::function<bool(const HttpResponse& head, const char* data, size_t n)> sink;
};

class HttpClient {
 public:
  HttpClient();
  ~HttpClient();
  HttpClient(HttpClient&&) noexcept;
  HttpClient& operator=(HttpClient&&) noexcept;

  HttpResult perform(const HttpRequest& request);

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

// Resolves a Location header against the URL it came from (absolute, host-relative or
// path-relative).
std::string url_join(const std::string& base, const std::string& location);
// "scheme://host:port" with the host lower-cased and the default port filled in; empty if
// unparsable.
std::string url_origin(const std::string& url);
// Lower-cased host name of a URL; empty if unparsable.
std::string url_host(const std::string& url);
// Percent-encodes everything but unreserved characters (and '/' when keep_slash).
std::string url_quote(const std::string& s, bool keep_slash);

}  // namespace tether::hub
