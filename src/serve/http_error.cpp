// The ErrorCode behind each HTTP status the server answers with, and the JSON of an error.
#include "serve/http_error.h"

#include <cstdio>

#include "text/unicode.h"

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

std::string printable_message(std::string_view message) {
  std::string out;
  out.reserve(message.size());
  for (std::size_t i = 0; i < message.size();) {
    const auto b = static_cast<unsigned char>(message[i]);
    const std::size_t len = text::utf8_len(b);
    const bool control = b < 0x20 || b == 0x7f;
    const bool valid = b < 0x80 ? !control
                                : i + len <= message.size() && len > 1 &&
                                      text::find_invalid_utf8(message.substr(i, len)) == std::string_view::npos;
    if (valid) {
      out.append(message.substr(i, len));
      i += len;
    } else {
      char hex[5];
      std::snprintf(hex, sizeof hex, "\\x%02x", b);
      out += hex;
      ++i;
    }
  }
  return out;
}

Json error_body(const std::string& code, const std::string& message) {
  return {{"error", {{"code", code}, {"message", message}}}};
}

}  // namespace tether::serve
