// UTF-8 iteration and the Unicode properties/normal forms the tokenizer pipeline needs
// (ICU-backed), each defined the way the Rust `tokenizers` crate's counterpart (std char methods,
// regex crate) is.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>

namespace tether::text {

// Byte offset of the first invalid sequence, or npos when `s` is valid UTF-8.
std::size_t find_invalid_utf8(std::string_view s);

// Length in bytes of the UTF-8 sequence starting with lead byte `b` (1 for ASCII/invalid leads).
inline std::size_t utf8_len(unsigned char b) {
  if (b < 0x80) return 1;
  if (b >= 0xF0) return 4;
  if (b >= 0xE0) return 3;
  if (b >= 0xC0) return 2;
  return 1;
}

// Decodes the code point at s[i] (s must be valid UTF-8); sets `len` to its byte length.
char32_t decode_utf8(std::string_view s, std::size_t i, std::size_t& len);
void append_utf8(std::string& out, char32_t c);

// Replaces each maximal invalid subsequence by U+FFFD, as Rust's String::from_utf8_lossy does.
std::string utf8_lossy(std::string_view bytes);

bool is_white_space(char32_t c);      // White_Space property (Rust char::is_whitespace, regex \s)
bool is_numeric(char32_t c);          // general category Nd | Nl | No (Rust char::is_numeric)
bool is_rust_regex_word(char32_t c);  // Rust regex crate's Unicode \w
// Python's str.isalnum (a letter or a number: general category L* or N*) and str.isspace (category Zs or
// bidirectional class WS, B or S), per character.
bool is_python_alnum(char32_t c);
bool is_python_space(char32_t c);

enum class NormalForm { nfc, nfd, nfkc, nfkd };
std::string normalize(std::string_view s, NormalForm form);
// Per-character full lowercase mapping without context (Rust char::to_lowercase).
std::string lowercase(std::string_view s);

}  // namespace tether::text
