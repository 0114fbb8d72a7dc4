// The ErrorCode behind each HTTP status the server answers with, and the JSON of an error.
#include "serve/http_error.h"

namespace tether::serve {

ErrorCode error_code_for_status(int status) {
  switch (status) {
    case 401: return ErrorCode::unauthenticated;
    case 404: return ErrorCode::not_found;
    case 408:
    case 504: return ErrorCode::timeout;
    case 503: return ErrorCode::unavailable;
    default: break;
  }
  if (status >= 400 && status < 500) return ErrorCode::invalid_argument;  // 400, 405, 413, 431: the request is wrong
  return ErrorCode::internal;  // 500 internal_error and inference_failed
}

Json error_body(const std::string& code, const std::string& message) {
  return {{"error", {{"code", code}, {"message", message}}}};
}

}  // namespace tether::serve
