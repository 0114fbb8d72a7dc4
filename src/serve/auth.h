// The API key check every transport applies to /act and /config: one comparison, one pair of messages.
#pragma once

#include <string>

namespace tether::serve {

// Constant-time in the length of `expected`: how long it takes says nothing about where `given` differs.
bool keys_equal(const std::string& given, const std::string& expected);

// Throws HttpError(401, "unauthorized") unless `expected` is empty (the server is open) or `presented` matches it.
// `presented`: the key the client sent, however its transport carries it (empty: none).
void check_api_key(const std::string& presented, const std::string& expected);

}  // namespace tether::serve
