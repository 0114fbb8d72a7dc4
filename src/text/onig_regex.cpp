// Tokenizer patterns on Oniguruma (the engine the Rust crate uses) or, for comparison, translated
// to PCRE2 (UTF + UCP, JIT when available).
#define PCRE2_CODE_UNIT_WIDTH 8
#include "text/onig_regex.h"

#include <oniguruma.h>
#include <pcre2.h>

#include <atomic>
#include <mutex>

#include "core/error.h"
#include "text/unicode.h"

namespace tether::text {

namespace {

// Oniguruma's Unicode \w is Letter | Mark | Number | Connector_Punctuation; PCRE2 10.42's lacks
// marks.
constexpr const char* kWordBody = "\\p{L}\\p{M}\\p{N}\\p{Pc}";

bool is_hex(char c) {
  return (c >= '0' && c <= '9') || (c >= 'a' && c <= 'f') || (c >= 'A' && c <= 'F');
}

std::string pcre2_error(int code) {
  PCRE2_UCHAR buf[256];
  pcre2_get_error_message(code, buf, sizeof(buf));
  return reinterpret_cast<const char*>(buf);
}

}  // namespace

std::string translate_onig_pattern(std::string_view p, const std::string& where) {
  auto unsupported = [&](const std::string& what) {
    return Error(ErrorCode::unsupported, where + ": regex '" + std::string(p) + "' uses " + what +
                                             ", which Tether's PCRE2 translation does not support");
  };
  std::string out;
  out.reserve(p.size() + 16);
  bool in_class = false;
  std::size_t class_open = 0;  // index just after '[' or '[^': a ']' there is a literal
  std::size_t i = 0;
  while (i < p.size()) {
    const char c = p[i];
    if (c == '\\') {
      if (i + 1 >= p.size())
        throw Error(ErrorCode::format, where + ": regex '" + std::string(p) + "' ends with '\\'");
      const char d = p[i + 1];
      // Oniguruma's \s is the White_Space property; PCRE2's also matches U+180E.
      if (d == 's') {
        out += "\\p{White_Space}";
      } else if (d == 'S') {
        out += "\\P{White_Space}";
      } else if (d == 'w') {
        out += in_class ? std::string(kWordBody) : "[" + std::string(kWordBody) + "]";
      } else if (d == 'W') {
        if (in_class) throw unsupported("\\W inside a character class");
        out += "[^" + std::string(kWordBody) + "]";
      } else if (d == 'h') {  // Ruby syntax: hexadecimal digit
        out += in_class ? "0-9a-fA-F" : "[0-9a-fA-F]";
      } else if (d == 'H') {
        if (in_class) throw unsupported("\\H inside a character class");
        out += "[^0-9a-fA-F]";
      } else if (d == 'u' && i + 6 <= p.size() && is_hex(p[i + 2]) && is_hex(p[i + 3]) &&
                 is_hex(p[i + 4]) && is_hex(p[i + 5])) {
        out += "\\x{" + std::string(p.substr(i + 2, 4)) + "}";
        i += 6;
        continue;
      } else {
        const std::size_t n = utf8_len(static_cast<unsigned char>(d));
        out += '\\';
        out.append(p.substr(i + 1, n));
        i += 1 + n;
        continue;
      }
      i += 2;
      continue;
    }
    if (in_class) {
      if (c == '[') {
        if (i + 1 < p.size() && p[i + 1] == ':') {
          const std::size_t end = p.find(":]", i + 2);
          if (end == std::string_view::npos) throw unsupported("an unterminated POSIX bracket");
          out.append(p.substr(i, end + 2 - i));
          i = end + 2;
          continue;
        }
        throw unsupported("a nested character class");
      }
      if (c == '&' && i + 1 < p.size() && p[i + 1] == '&')
        throw unsupported("character class intersection (&&)");
      if (c == ']' && i != class_open) in_class = false;
      out += c;
      ++i;
      continue;
    }
    if (c == '[') {
      in_class = true;
      out += c;
      ++i;
      if (i < p.size() && p[i] == '^') out += p[i++];
      class_open = i;
      continue;
    }
    if (c == '(' && i + 1 < p.size() && p[i + 1] == '?') {
      // Inline options: Ruby's (?m) is "dot matches newline", PCRE2's (?s).
      std::size_t j = i + 2;
      while (j < p.size() && (p[j] == 'i' || p[j] == 'm' || p[j] == 'x' || p[j] == '-')) ++j;
      if (j > i + 2 && j < p.size() && (p[j] == ':' || p[j] == ')')) {
        out += "(?";
        for (std::size_t k = i + 2; k < j; ++k) out += p[k] == 'm' ? 's' : p[k];
        i = j;
        continue;
      }
    }
    const std::size_t n = utf8_len(static_cast<unsigned char>(c));
    out.append(p.substr(i, n));
    i += n;
  }
  return out;
}

namespace detail {
namespace {
std::atomic<RegexEngine> g_engine{RegexEngine::oniguruma};
}
void set_regex_engine(RegexEngine e) { g_engine.store(e); }
RegexEngine regex_engine() { return g_engine.load(); }
}  // namespace detail

namespace {

std::string onig_error(int code, OnigErrorInfo* info) {
  OnigUChar buf[ONIG_MAX_ERROR_MESSAGE_LEN];
  const int n = info ? onig_error_code_to_str(buf, code, info) : onig_error_code_to_str(buf, code);
  return std::string(reinterpret_cast<const char*>(buf), n > 0 ? static_cast<std::size_t>(n) : 0);
}

void init_oniguruma() {
  static std::once_flag once;
  std::call_once(once, [] {
    OnigEncoding encodings[] = {ONIG_ENCODING_UTF8};
    onig_initialize(encodings, 1);
  });
}

// The Rust `regex` crate's escape(), which the crate applies to String patterns.
bool is_rust_regex_meta(char c) {
  switch (c) {
    case '\\': case '.': case '+': case '*': case '?': case '(': case ')': case '|': case '[':
    case ']': case '{': case '}': case '^': case '$': case '#': case '&': case '-': case '~':
      return true;
    default:
      return false;
  }
}

}  // namespace

struct OnigRegex::Compiled {
  RegexEngine engine = RegexEngine::oniguruma;
  regex_t* onig = nullptr;
  pcre2_code* code = nullptr;
  bool jit = false;
  ~Compiled() {
    if (onig) onig_free(onig);
    if (code) pcre2_code_free(code);
  }
};

OnigRegex::OnigRegex(const std::string& onig_pattern, const std::string& where)
    : compiled_(new Compiled) {
  compiled_->engine = detail::regex_engine();
  if (compiled_->engine == RegexEngine::oniguruma) {
    init_oniguruma();
    // As the onig crate's Regex::new: no options, the default (Oniguruma) syntax, UTF-8.
    OnigErrorInfo info{};
    const auto* p = reinterpret_cast<const OnigUChar*>(onig_pattern.data());
    const int rc = onig_new(&compiled_->onig, p, p + onig_pattern.size(), ONIG_OPTION_NONE,
                            ONIG_ENCODING_UTF8, ONIG_SYNTAX_DEFAULT, &info);
    if (rc != ONIG_NORMAL) {
      compiled_->onig = nullptr;
      throw Error(ErrorCode::format, where + ": cannot compile regex '" + onig_pattern +
                                         "': " + onig_error(rc, &info));
    }
    return;
  }
  const std::string pattern = translate_onig_pattern(onig_pattern, where);
  pcre2_compile_context* ctx = pcre2_compile_context_create(nullptr);
  pcre2_set_newline(ctx, PCRE2_NEWLINE_LF);  // onig: only "\n" ends a line for ^ $ and .
  int err = 0;
  PCRE2_SIZE err_offset = 0;
  // Ruby syntax: ^ and $ are always line anchors.
  compiled_->code = pcre2_compile(reinterpret_cast<PCRE2_SPTR>(pattern.data()), pattern.size(),
                                  PCRE2_UTF | PCRE2_UCP | PCRE2_MULTILINE, &err, &err_offset, ctx);
  pcre2_compile_context_free(ctx);
  if (!compiled_->code) {
    throw Error(ErrorCode::format, where + ": cannot compile regex '" + onig_pattern +
                                       "' (as PCRE2 '" + pattern + "'): " + pcre2_error(err) +
                                       " at offset " + std::to_string(err_offset));
  }
  compiled_->jit = pcre2_jit_compile(compiled_->code, PCRE2_JIT_COMPLETE) == 0;
}

OnigRegex OnigRegex::literal(std::string_view literal, const std::string& where) {
  std::string escaped;
  if (detail::regex_engine() == RegexEngine::oniguruma) {
    for (char c : literal) {
      if (is_rust_regex_meta(c)) escaped += '\\';
      escaped += c;
    }
    return OnigRegex(escaped, where);
  }
  for (char c : literal) {
    const auto u = static_cast<unsigned char>(c);
    if (u < 0x80 && !((c >= '0' && c <= '9') || (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z'))) {
      if (c == '\n') {
        escaped += "\\n";
      } else if (u < 0x20 || u == 0x7F) {
        static const char* hex = "0123456789ABCDEF";
        escaped += "\\x{";
        escaped += hex[u >> 4];
        escaped += hex[u & 15];
        escaped += '}';
      } else {
        escaped += '\\';
        escaped += c;
      }
    } else {
      escaped += c;
    }
  }
  return OnigRegex(escaped, where);
}

OnigRegex::~OnigRegex() = default;
OnigRegex::OnigRegex(OnigRegex&&) noexcept = default;
OnigRegex& OnigRegex::operator=(OnigRegex&&) noexcept = default;

namespace {

struct MatchDataDeleter {
  void operator()(pcre2_match_data* m) const { pcre2_match_data_free(m); }
};

pcre2_match_data* thread_match_data() {
  // Only the whole-match offsets are read, so one pair serves every pattern.
  thread_local std::unique_ptr<pcre2_match_data, MatchDataDeleter> data(
      pcre2_match_data_create(1, nullptr));
  return data.get();
}

struct RegionDeleter {
  void operator()(OnigRegion* r) const { onig_region_free(r, 1); }
};

OnigRegion* thread_region() {
  thread_local std::unique_ptr<OnigRegion, RegionDeleter> region(onig_region_new());
  return region.get();
}

}  // namespace

// The onig crate's FindMatches: search from the end of the previous match over the whole text
// (so anchors and look-behind see it), never yielding an empty match right where the previous
// match ended (it steps one character forward and searches again).
std::vector<std::pair<std::size_t, std::size_t>> OnigRegex::find_all(std::string_view text) const {
  std::vector<std::pair<std::size_t, std::size_t>> out;
  if (compiled_->engine == RegexEngine::oniguruma) {
    OnigRegion* region = thread_region();
    const auto* str = reinterpret_cast<const OnigUChar*>(text.data());
    const OnigUChar* end = str + text.size();
    std::size_t last_end = 0;
    bool have_last = false;
    std::size_t last_match_end = 0;
    while (last_end <= text.size()) {
      onig_region_clear(region);
      const int rc =
          onig_search(compiled_->onig, str, end, str + last_end, end, region, ONIG_OPTION_NONE);
      if (rc == ONIG_MISMATCH) break;
      if (rc < 0) throw Error(ErrorCode::internal, "regex search failed: " + onig_error(rc, nullptr));
      const auto s = static_cast<std::size_t>(region->beg[0]);
      const auto e = static_cast<std::size_t>(region->end[0]);
      if (s == e && have_last && last_match_end == e) {
        last_end += last_end < text.size() ? utf8_len(static_cast<unsigned char>(text[last_end])) : 1;
        continue;
      }
      last_end = e;
      have_last = true;
      last_match_end = e;
      out.emplace_back(s, e);
    }
    return out;
  }
  pcre2_match_data* md = thread_match_data();
  const auto* subject = reinterpret_cast<PCRE2_SPTR>(text.data());
  std::size_t last_end = 0;
  bool have_last = false;
  std::size_t last_match_end = 0;
  while (last_end <= text.size()) {
    int rc;
    if (compiled_->jit) {
      rc = pcre2_jit_match(compiled_->code, subject, text.size(), last_end, 0, md, nullptr);
      if (rc == PCRE2_ERROR_JIT_STACKLIMIT)
        rc = pcre2_match(compiled_->code, subject, text.size(), last_end,
                         PCRE2_NO_JIT | PCRE2_NO_UTF_CHECK, md, nullptr);
    } else {
      rc = pcre2_match(compiled_->code, subject, text.size(), last_end, PCRE2_NO_UTF_CHECK, md,
                       nullptr);
    }
    if (rc == PCRE2_ERROR_NOMATCH) break;
    if (rc < 0) throw Error(ErrorCode::internal, "regex match failed: " + pcre2_error(rc));
    const PCRE2_SIZE* ov = pcre2_get_ovector_pointer(md);
    const std::size_t s = ov[0], e = ov[1];
    // The onig crate never yields an empty match right where the previous match ended; it steps
    // one character forward and searches again.
    if (s == e && have_last && last_match_end == e) {
      last_end += last_end < text.size() ? utf8_len(static_cast<unsigned char>(text[last_end])) : 1;
      continue;
    }
    last_end = e;
    have_last = true;
    last_match_end = e;
    out.emplace_back(s, e);
  }
  return out;
}

}  // namespace tether::text
