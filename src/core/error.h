// Errors raised across Tether: a stable code plus a message that names the file, tensor or field at fault.
#pragma once

#include <stdexcept>
#include <string>

namespace tether {

enum class ErrorCode {
  invalid_argument,  // caller passed something malformed (bad shape, unknown camera, bad flag)
  not_found,         // a file, tensor or field that should exist does not
  io,                // the OS refused: open, read, mmap
  format,            // a file exists but its contents are malformed or lie about themselves
  unsupported,       // well-formed, but Tether does not implement it (yet)
  internal,          // a bug: an invariant inside Tether broke
  unauthenticated,   // a request without the API key the server requires, or with a wrong one
  unavailable,       // cannot serve now but may shortly: a full queue, a model not ready, an open circuit
  timeout,           // a deadline passed before the work finished
};

const char* error_code_name(ErrorCode code);

class Error : public std::runtime_error {
 public:
  Error(ErrorCode code, const std::string& message) : std::runtime_error(message), code_(code) {}
  ErrorCode code() const { return code_; }

 private:
  ErrorCode code_;
};

}  // namespace tether
