// Base64 through EVP_DecodeBlock/EVP_EncodeBlock. OpenSSL is lenient where Tether is strict: it trims leading and
// trailing whitespace, reads '=' anywhere as a zero group and never reports padding, so those checks are made here
// (cheaply: the ends, one memchr) and the group-by-group work is the library's.
#include "serve/base64.h"

#include <openssl/evp.h>

#include <algorithm>
#include <climits>
#include <cstring>

namespace tether::serve {

namespace {

bool in_alphabet(char c) {
  return (c >= 'A' && c <= 'Z') || (c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '+' || c == '/';
}

// Largest input handed to one EVP_DecodeBlock call: a multiple of 4 that fits its int length.
constexpr std::size_t kMaxBlockChars = std::size_t(INT_MAX / 4) * 4;

}  // namespace

std::optional<std::vector<uint8_t>> base64_decode(std::string_view text, std::string* why) {
  auto fail = [&](const std::string& msg) -> std::optional<std::vector<uint8_t>> {
    if (why) *why = msg;
    return std::nullopt;
  };
  auto first_invalid = [&](std::size_t n) {
    std::size_t i = 0;
    while (i < n && in_alphabet(text[i])) ++i;
    return fail("invalid base64 character at offset " + std::to_string(i));
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

  const std::size_t whole = n / 4 * 4;  // full groups; the last 2 or 3 characters (if any) are decoded below
  std::vector<uint8_t> out(whole / 4 * 3 + 2);
  const auto* in = reinterpret_cast<const unsigned char*>(text.data());
  // OpenSSL would trim whitespace at either end of a block and accept '=' inside it: neither may pass.
  if (n > 0 && (!in_alphabet(text[0]) || !in_alphabet(text[n - 1]))) return first_invalid(n);
  if (std::memchr(text.data(), '=', n) != nullptr) return first_invalid(n);
  std::size_t written = 0;
  for (std::size_t at = 0; at < whole;) {
    const std::size_t len = std::min(kMaxBlockChars, whole - at);
    // Block boundaries inside the text must not be trimmed either.
    if (!in_alphabet(text[at]) || !in_alphabet(text[at + len - 1])) return first_invalid(n);
    const int got = EVP_DecodeBlock(out.data() + written, in + at, int(len));
    if (got < 0) return first_invalid(n);
    written += std::size_t(got);
    at += len;
  }
  if (const std::size_t tail = n - whole; tail > 0) {
    // 2 or 3 characters: completed with 'A' (zero bits) into one group, whose unused bits must then be zero.
    unsigned char group[4] = {'A', 'A', 'A', 'A'};
    std::memcpy(group, in + whole, tail);
    unsigned char bytes[3];
    if (EVP_DecodeBlock(bytes, group, 4) != 3) return first_invalid(n);
    const std::size_t keep = tail - 1;  // 2 characters carry 1 byte, 3 carry 2
    // Canonical encodings leave the unused low bits of the last character zero; anything else is corruption.
    for (std::size_t i = keep; i < 3; ++i)
      if (bytes[i] != 0) return fail("base64 ends with non-zero padding bits (truncated or corrupted data)");
    std::memcpy(out.data() + written, bytes, keep);
    written += keep;
  }
  out.resize(written);
  return out;
}

std::string base64_encode(const uint8_t* bytes, std::size_t size) {
  std::string out;
  // EVP_EncodeBlock writes a terminating NUL after the 4-character groups; it is trimmed off.
  constexpr std::size_t kMaxBlockBytes = std::size_t(INT_MAX / 4 / 3) * 3;  // whole groups, output within int
  out.resize((size + 2) / 3 * 4 + 1);
  std::size_t written = 0;
  for (std::size_t at = 0; at < size;) {
    const std::size_t len = std::min(kMaxBlockBytes, size - at);
    written += std::size_t(EVP_EncodeBlock(reinterpret_cast<unsigned char*>(out.data()) + written, bytes + at, int(len)));
    at += len;
  }
  out.resize(written);
  return out;
}

}  // namespace tether::serve
