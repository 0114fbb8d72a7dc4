// A request that cannot be served: the HTTP status, the stable machine-readable code clients branch on, and a
// sentence for humans.
#pragma once

#include <stdexcept>
#include <string>

namespace tether::serve {

class HttpError : public std::runtime_error {
 public:
  HttpError(int status, std::string code, const std::string& message)
      : std::runtime_error(message), status_(status), code_(std::move(code)) {}
  int status() const { return status_; }
  const std::string& code() const { return code_; }

 private:
  int status_;
  std::string code_;
};

}  // namespace tether::serve
