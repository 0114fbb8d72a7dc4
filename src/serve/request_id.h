// Request ids: accepting a client's, minting fresh ones, and the default noise seed derived from one.
#pragma once

#include <cstdint>
#include <initializer_list>
#include <string>

namespace tether::serve {

// Accepts a client-supplied request id only if it is 1..128 characters of [A-Za-z0-9._:-].
bool valid_request_id(const std::string& id);
// A fresh id: 16 hex digits, unique within the process and unlike the previous one.
std::string generate_request_id();
// The first valid id among those a client offered (in order of preference), else a fresh one.
std::string request_id_or_new(std::initializer_list<std::string> offered);
// A default noise seed from a request id (FNV-1a), so a logged id reproduces the request's noise.
uint64_t seed_from_request_id(const std::string& id);

}  // namespace tether::serve
