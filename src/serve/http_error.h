// A request that cannot be served: the HTTP status, the stable machine-readable code clients branch on, and a
// sentence for humans. A tether::Error whose ErrorCode follows from the status.
#pragma once

#include <string>
#include <string_view>

#include "core/error.h"
#include "core/json_util.h"

namespace tether::serve {

// The tether::ErrorCode a response status is reported under (400 -> invalid_argument, 503 -> unavailable, ...).
ErrorCode error_code_for_status(int status);

// `message` as text any client can be sent: control bytes and bytes that are not UTF-8 written as \xNN, valid UTF-8
// kept. Messages quote names the client chose (msgpack keys, cameras), which may hold anything: a NUL would cut
// what() short, and a WebSocket text frame (openpi's failure shape) or a msgpack str must be UTF-8.
std::string printable_message(std::string_view message);

class HttpError : public Error {
 public:
  // `retry_after_s`: the Retry-After a 503 carries (1 s unless the cause knows better, e.g. an open circuit).
  HttpError(int status, std::string code, const std::string& message, int retry_after_s = 1)
      : Error(error_code_for_status(status), printable_message(message)),
        status_(status),
        code_(std::move(code)),
        retry_after_s_(retry_after_s) {}
  int status() const { return status_; }
  const std::string& code() const { return code_; }
  int retry_after_s() const { return retry_after_s_; }

 private:
  int status_;
  std::string code_;
  int retry_after_s_;
};

// The body every error response carries, whatever the transport: {"error": {"code": ..., "message": ...}}.
Json error_body(const std::string& code, const std::string& message);

}  // namespace tether::serve
