// A request that cannot be served: the HTTP status, the stable machine-readable code clients branch on, and a
// sentence for humans. A tether::Error whose ErrorCode follows from the status.
#pragma once

#include <string>

#include "core/error.h"
#include "core/json_util.h"

namespace tether::serve {

// The tether::ErrorCode a response status is reported under (400 -> invalid_argument, 503 -> unavailable, ...).
ErrorCode error_code_for_status(int status);

class HttpError : public Error {
 public:
  // `retry_after_s`: the Retry-After a 503 carries (1 s unless the cause knows better, e.g. an open circuit).
  HttpError(int status, std::string code, const std::string& message, int retry_after_s = 1)
      : Error(error_code_for_status(status), message),
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
