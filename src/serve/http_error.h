// A request that cannot be served: the HTTP status, the stable machine-readable code clients branch on, and a
// sentence for humans.
#pragma once

#include <stdexcept>
#include <string>

namespace tether::serve {

class HttpError : public std::runtime_error {
 public:
  // `retry_after_s`: the Retry-After a 503 carries (1 s unless the cause knows better, e.g. an open circuit).
  HttpError(int status, std::string code, const std::string& message, int retry_after_s = 1)
      : std::runtime_error(message), status_(status), code_(std::move(code)), retry_after_s_(retry_after_s) {}
  int status() const { return status_; }
  const std::string& code() const { return code_; }
  int retry_after_s() const { return retry_after_s_; }

 private:
  int status_;
  std::string code_;
  int retry_after_s_;
};

}  // namespace tether::serve
