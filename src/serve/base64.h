// Base64 (RFC 4648 standard alphabet) for image payloads in requests: a strict decoder (its errors say what is wrong
// and where) and OpenSSL's block encoder.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

namespace tether::serve {

// Decodes `text`; padding is optional, whitespace and the URL-safe alphabet are not accepted. On malformed input
// returns nullopt and, when `why` is given, a sentence saying what and where.
std::optional<std::vector<uint8_t>> base64_decode(std::string_view text, std::string* why = nullptr);
std::string base64_encode(const uint8_t* bytes, std::size_t size);

}  // namespace tether::serve
