// ICU-backed Unicode helpers for the tokenizer; see unicode.h for which Rust behaviour each
// mirrors.
#include "text/unicode.h"

#include <unicode/uchar.h>
#include <unicode/unorm2.h>
#include <unicode/uset.h>
#include <unicode/ustring.h>

#include "core/error.h"

namespace tether::text {

namespace {

// Length of the valid prefix of the sequence at s[i] (0 when s[i] cannot start one) and whether
// that prefix is a complete character; the bounds are those of Unicode's well-formed table.
std::size_t valid_prefix(std::string_view s, std::size_t i, bool& complete) {
  const auto b0 = static_cast<unsigned char>(s[i]);
  complete = false;
  std::size_t need;
  unsigned char lo = 0x80, hi = 0xBF;
  if (b0 < 0x80) {
    complete = true;
    return 1;
  } else if (b0 >= 0xC2 && b0 <= 0xDF) {
    need = 2;
  } else if (b0 >= 0xE0 && b0 <= 0xEF) {
    need = 3;
    if (b0 == 0xE0) lo = 0xA0;
    if (b0 == 0xED) hi = 0x9F;
  } else if (b0 >= 0xF0 && b0 <= 0xF4) {
    need = 4;
    if (b0 == 0xF0) lo = 0x90;
    if (b0 == 0xF4) hi = 0x8F;
  } else {
    return 0;
  }
  std::size_t n = 1;
  while (n < need && i + n < s.size()) {
    const auto b = static_cast<unsigned char>(s[i + n]);
    const unsigned char l = n == 1 ? lo : 0x80, h = n == 1 ? hi : 0xBF;
    if (b < l || b > h) break;
    ++n;
  }
  complete = n == need;
  return n;
}

std::u16string to_utf16(std::string_view s) {
  std::u16string out(s.size(), u'\0');
  int32_t len = 0;
  UErrorCode err = U_ZERO_ERROR;
  u_strFromUTF8(reinterpret_cast<UChar*>(out.data()), static_cast<int32_t>(out.size()), &len,
                s.data(), static_cast<int32_t>(s.size()), &err);
  if (U_FAILURE(err))
    throw Error(ErrorCode::internal, std::string("UTF-8 to UTF-16 failed: ") + u_errorName(err));
  out.resize(static_cast<std::size_t>(len));
  return out;
}

std::string to_utf8(const UChar* s, int32_t n) {
  std::string out(static_cast<std::size_t>(n) * 3, '\0');
  int32_t len = 0;
  UErrorCode err = U_ZERO_ERROR;
  u_strToUTF8(out.data(), static_cast<int32_t>(out.size()), &len, s, n, &err);
  if (U_FAILURE(err))
    throw Error(ErrorCode::internal, std::string("UTF-16 to UTF-8 failed: ") + u_errorName(err));
  out.resize(static_cast<std::size_t>(len));
  return out;
}

bool is_ascii(std::string_view s) {
  for (char c : s)
    if (static_cast<unsigned char>(c) >= 0x80) return false;
  return true;
}

// The crate normalises with tables from Unicode 9.0 (checked per code point against the Python
// package: it lacks the combining classes of Unicode 10.0 marks such as U+0D3B). Characters
// assigned later are passed through untouched, which is how those tables treat them.
const UNormalizer2* filtered_normalizer(NormalForm form) {
  struct Filtered {
    USet* set = nullptr;
    const UNormalizer2* forms[4] = {};
    Filtered() {
      UErrorCode err = U_ZERO_ERROR;
      const std::u16string pattern = u"[:Age=9.0:]";
      set = uset_openPattern(reinterpret_cast<const UChar*>(pattern.data()),
                             static_cast<int32_t>(pattern.size()), &err);
      if (U_FAILURE(err))
        throw Error(ErrorCode::internal,
                    std::string("ICU age set unavailable: ") + u_errorName(err));
      uset_freeze(set);
      const UNormalizer2* base[4] = {unorm2_getNFCInstance(&err), unorm2_getNFDInstance(&err),
                                     unorm2_getNFKCInstance(&err), unorm2_getNFKDInstance(&err)};
      if (U_FAILURE(err))
        throw Error(ErrorCode::internal,
                    std::string("ICU normalizer unavailable: ") + u_errorName(err));
      for (int k = 0; k < 4; ++k) {
        forms[k] = unorm2_openFiltered(base[k], set, &err);
        if (U_FAILURE(err))
          throw Error(ErrorCode::internal,
                      std::string("ICU filtered normalizer: ") + u_errorName(err));
      }
    }
  };
  static const Filtered filtered;  // process lifetime: ICU objects are immutable and thread-safe
  return filtered.forms[static_cast<int>(form)];
}

}  // namespace

std::size_t find_invalid_utf8(std::string_view s) {
  std::size_t i = 0;
  while (i < s.size()) {
    bool complete;
    const std::size_t n = valid_prefix(s, i, complete);
    if (!complete) return i;
    i += n;
  }
  return std::string_view::npos;
}

char32_t decode_utf8(std::string_view s, std::size_t i, std::size_t& len) {
  const auto b0 = static_cast<unsigned char>(s[i]);
  len = utf8_len(b0);
  if (len == 1) return b0;
  char32_t c = b0 & (0xFF >> (len + 1));
  for (std::size_t k = 1; k < len; ++k)
    c = (c << 6) | (static_cast<unsigned char>(s[i + k]) & 0x3F);
  return c;
}

void append_utf8(std::string& out, char32_t c) {
  if (c < 0x80) {
    out.push_back(static_cast<char>(c));
  } else if (c < 0x800) {
    out.push_back(static_cast<char>(0xC0 | (c >> 6)));
    out.push_back(static_cast<char>(0x80 | (c & 0x3F)));
  } else if (c < 0x10000) {
    out.push_back(static_cast<char>(0xE0 | (c >> 12)));
    out.push_back(static_cast<char>(0x80 | ((c >> 6) & 0x3F)));
    out.push_back(static_cast<char>(0x80 | (c & 0x3F)));
  } else {
    out.push_back(static_cast<char>(0xF0 | (c >> 18)));
    out.push_back(static_cast<char>(0x80 | ((c >> 12) & 0x3F)));
    out.push_back(static_cast<char>(0x80 | ((c >> 6) & 0x3F)));
    out.push_back(static_cast<char>(0x80 | (c & 0x3F)));
  }
}

std::string utf8_lossy(std::string_view bytes) {
  std::string out;
  out.reserve(bytes.size());
  std::size_t i = 0;
  while (i < bytes.size()) {
    bool complete;
    const std::size_t n = valid_prefix(bytes, i, complete);
    if (complete) {
      out.append(bytes.substr(i, n));
      i += n;
    } else {
      out.append("\xEF\xBF\xBD");
      i += n == 0 ? 1 : n;
    }
  }
  return out;
}

bool is_white_space(char32_t c) {
  if (c < 0x80) return c == ' ' || (c >= 0x09 && c <= 0x0D);
  return u_hasBinaryProperty(static_cast<UChar32>(c), UCHAR_WHITE_SPACE);
}

bool is_numeric(char32_t c) {
  if (c < 0x80) return c >= '0' && c <= '9';
  const int8_t t = u_charType(static_cast<UChar32>(c));
  return t == U_DECIMAL_DIGIT_NUMBER || t == U_LETTER_NUMBER || t == U_OTHER_NUMBER;
}

bool is_python_alnum(char32_t c) {
  if (c < 0x80) return (c >= '0' && c <= '9') || (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z');
  const uint32_t mask = U_MASK(u_charType(static_cast<UChar32>(c)));
  return (mask & (U_GC_L_MASK | U_GC_N_MASK)) != 0;
}

bool is_python_space(char32_t c) {
  if (u_charType(static_cast<UChar32>(c)) == U_SPACE_SEPARATOR) return true;
  const UCharDirection d = u_charDirection(static_cast<UChar32>(c));
  return d == U_WHITE_SPACE_NEUTRAL || d == U_BLOCK_SEPARATOR || d == U_SEGMENT_SEPARATOR;
}

bool is_rust_regex_word(char32_t c) {
  if (c < 0x80)
    return (c >= '0' && c <= '9') || (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || c == '_';
  const auto u = static_cast<UChar32>(c);
  if (u_hasBinaryProperty(u, UCHAR_ALPHABETIC) || u_hasBinaryProperty(u, UCHAR_JOIN_CONTROL))
    return true;
  const int8_t t = u_charType(u);
  return t == U_NON_SPACING_MARK || t == U_ENCLOSING_MARK || t == U_COMBINING_SPACING_MARK ||
         t == U_DECIMAL_DIGIT_NUMBER || t == U_CONNECTOR_PUNCTUATION;
}

std::string normalize(std::string_view s, NormalForm form) {
  if (is_ascii(s)) return std::string(s);  // ASCII is stable under all four forms
  const UNormalizer2* n = filtered_normalizer(form);
  UErrorCode err = U_ZERO_ERROR;
  const std::u16string src = to_utf16(s);
  // NFKD can expand one code unit into up to 18; retry once with the size ICU asks for.
  std::u16string dst(src.size() * 3 + 16, u'\0');
  int32_t len = unorm2_normalize(
      n, reinterpret_cast<const UChar*>(src.data()), static_cast<int32_t>(src.size()),
      reinterpret_cast<UChar*>(dst.data()), static_cast<int32_t>(dst.size()), &err);
  if (err == U_BUFFER_OVERFLOW_ERROR) {
    err = U_ZERO_ERROR;
    dst.assign(static_cast<std::size_t>(len), u'\0');
    len = unorm2_normalize(n, reinterpret_cast<const UChar*>(src.data()),
                           static_cast<int32_t>(src.size()), reinterpret_cast<UChar*>(dst.data()),
                           static_cast<int32_t>(dst.size()), &err);
  }
  if (U_FAILURE(err))
    throw Error(ErrorCode::internal, std::string("ICU normalization failed: ") + u_errorName(err));
  return to_utf8(reinterpret_cast<const UChar*>(dst.data()), len);
}

std::string lowercase(std::string_view s) {
  std::string out;
  out.reserve(s.size());
  std::size_t i = 0;
  while (i < s.size()) {
    std::size_t n;
    const char32_t c = decode_utf8(s, i, n);
    i += n;
    if (c < 0x80) {
      out.push_back(static_cast<char>(c >= 'A' && c <= 'Z' ? c + 32 : c));
      continue;
    }
    // One character at a time, so context-dependent rules (final sigma) see no context, which is
    // what a per-char mapping does.
    UChar src[2];
    int32_t src_len = 0;
    U16_APPEND_UNSAFE(src, src_len, static_cast<UChar32>(c));
    UChar dst[8];
    UErrorCode err = U_ZERO_ERROR;
    const int32_t len = u_strToLower(dst, 8, src, src_len, "", &err);
    if (U_FAILURE(err))
      throw Error(ErrorCode::internal, std::string("ICU lowercase failed: ") + u_errorName(err));
    out += to_utf8(dst, len);
  }
  return out;
}

}  // namespace tether::text
