// API key comparison and the 401 it leads to.
#include "serve/auth.h"

#include "serve/http_error.h"

namespace tether::serve {

bool keys_equal(const std::string& given, const std::string& expected) {
  // Every byte of `expected` is visited whatever `given` holds; a length mismatch is folded into the same result.
  unsigned char diff = given.size() == expected.size() ? 0 : 1;
  for (std::size_t i = 0; i < expected.size(); ++i) {
    const unsigned char g = i < given.size() ? static_cast<unsigned char>(given[i]) : 0;
    diff |= static_cast<unsigned char>(g ^ static_cast<unsigned char>(expected[i]));
  }
  return diff == 0;
}

void check_api_key(const std::string& presented, const std::string& expected) {
  if (expected.empty()) return;
  if (presented.empty() || !keys_equal(presented, expected))
    throw HttpError(401, "unauthorized",
                    presented.empty() ? "an API key is required (Authorization: Bearer <key> or X-Tether-Key)"
                                      : "the API key is not valid");
}

}  // namespace tether::serve
