// Base64 codec: a 256-entry reverse table, four characters to three bytes.
#include "serve/base64.h"

#include <array>

namespace tether::serve {

namespace {

constexpr char kAlphabet[] = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";

constexpr std::array<int8_t, 256> make_reverse() {
  std::array<int8_t, 256> r{};
  for (auto& v : r) v = -1;
  for (int i = 0; i < 64; ++i) r[uint8_t(kAlphabet[i])] = int8_t(i);
  return r;
}
constexpr std::array<int8_t, 256> kReverse = make_reverse();

}  // namespace

std::optional<std::vector<uint8_t>> base64_decode(std::string_view text, std::string* why) {
  auto fail = [&](const std::string& msg) -> std::optional<std::vector<uint8_t>> {
    if (why) *why = msg;
    return std::nullopt;
  };
  std::size_t n = text.size();
  // Up to two '=' at the very end; anywhere else they are an error like any other stray character.
  std::size_t pad = 0;
  while (pad < 2 && n > 0 && text[n - 1] == '=') {
    --n;
    ++pad;
  }
  if (pad > 0 && (n + pad) % 4 != 0) return fail("base64 padding does not complete a 4-character group");
  if (n % 4 == 1) return fail("base64 length " + std::to_string(text.size()) + " is impossible (a lone 6-bit group)");
  std::vector<uint8_t> out;
  out.reserve(n / 4 * 3 + 2);
  uint32_t acc = 0;
  int bits = 0;
  for (std::size_t i = 0; i < n; ++i) {
    const int8_t v = kReverse[uint8_t(text[i])];
    if (v < 0) return fail("invalid base64 character at offset " + std::to_string(i));
    acc = (acc << 6) | uint32_t(v);
    bits += 6;
    if (bits >= 8) {
      bits -= 8;
      out.push_back(uint8_t(acc >> bits));
      acc &= (1u << bits) - 1;
    }
  }
  // Canonical encodings leave the unused low bits of the last character zero; anything else is corruption.
  if (acc != 0) return fail("base64 ends with non-zero padding bits (truncated or corrupted data)");
  return out;
}

std::string base64_encode(const uint8_t* bytes, std::size_t size) {
  std::string out;
  out.reserve((size + 2) / 3 * 4);
  std::size_t i = 0;
  for (; i + 3 <= size; i += 3) {
    const uint32_t v = uint32_t(bytes[i]) << 16 | uint32_t(bytes[i + 1]) << 8 | bytes[i + 2];
    out += kAlphabet[v >> 18];
    out += kAlphabet[(v >> 12) & 63];
    out += kAlphabet[(v >> 6) & 63];
    out += kAlphabet[v & 63];
  }
  if (size - i == 1) {
    const uint32_t v = uint32_t(bytes[i]) << 16;
    out += kAlphabet[v >> 18];
    out += kAlphabet[(v >> 12) & 63];
    out += "==";
  } else if (size - i == 2) {
    const uint32_t v = uint32_t(bytes[i]) << 16 | uint32_t(bytes[i + 1]) << 8;
    out += kAlphabet[v >> 18];
    out += kAlphabet[(v >> 12) & 63];
    out += kAlphabet[(v >> 6) & 63];
    out += '=';
  }
  return out;
}

}  // namespace tether::serve
