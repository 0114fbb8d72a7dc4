// Oniguruma (UTF-8, default syntax, no options: the onig crate's Regex::new) running tokenizer
// patterns, with the onig crate's handling of empty matches.
#include "text/onig_regex.h"

#include <oniguruma.h>

#include <cstdio>
#include <mutex>

#include "core/error.h"
#include "text/unicode.h"

namespace tether::text {

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

// The characters the Rust `regex` crate's escape() prefixes with '\', as the crate does to a
// String pattern before compiling it.
bool is_rust_regex_meta(char c) {
  switch (c) {
    case '\\': case '.': case '+': case '*': case '?': case '(': case ')': case '|': case '[':
    case ']': case '{': case '}': case '^': case '$': case '#': case '&': case '-': case '~':
      return true;
    default:
      return false;
  }
}

struct RegionDeleter {
  void operator()(OnigRegion* r) const { onig_region_free(r, 1); }
};

OnigRegion* thread_region() {
  // Only the whole-match offsets are read; one region per thread serves every pattern.
  thread_local std::unique_ptr<OnigRegion, RegionDeleter> region(onig_region_new());
  return region.get();
}

}  // namespace

struct OnigRegex::Compiled {
  regex_t* re = nullptr;
  ~Compiled() {
    if (re) onig_free(re);
  }
};

OnigRegex::OnigRegex(const std::string& onig_pattern, const std::string& where)
    : compiled_(new Compiled) {
  init_oniguruma();
  OnigErrorInfo info{};
  const auto* p = reinterpret_cast<const OnigUChar*>(onig_pattern.data());
  const int rc = onig_new(&compiled_->re, p, p + onig_pattern.size(), ONIG_OPTION_NONE,
                          ONIG_ENCODING_UTF8, ONIG_SYNTAX_DEFAULT, &info);
  if (rc != ONIG_NORMAL) {
    compiled_->re = nullptr;
    throw Error(ErrorCode::format,
                where + ": cannot compile regex '" + onig_pattern + "': " + onig_error(rc, &info));
  }
}

OnigRegex OnigRegex::literal(std::string_view literal, const std::string& where) {
  std::string escaped;
  escaped.reserve(literal.size() * 2);
  for (char c : literal) {
    if (is_rust_regex_meta(c)) escaped += '\\';
    escaped += c;
  }
  return OnigRegex(escaped, where);
}

OnigRegex::~OnigRegex() = default;
OnigRegex::OnigRegex(OnigRegex&&) noexcept = default;
OnigRegex& OnigRegex::operator=(OnigRegex&&) noexcept = default;

// The onig crate's FindMatches: each search runs over the whole text from the end of the previous
// match (so anchors and look-behind see what precedes it), and an empty match right where the
// previous match ended is not yielded: the search steps one character forward and runs again.
std::vector<std::pair<std::size_t, std::size_t>> OnigRegex::find_all(std::string_view text) const {
  std::vector<std::pair<std::size_t, std::size_t>> out;
  OnigRegion* region = thread_region();
  const auto* str = reinterpret_cast<const OnigUChar*>(text.data());
  const OnigUChar* end = str + text.size();
  std::size_t last_end = 0;
  bool have_last = false;
  std::size_t last_match_end = 0;
  while (last_end <= text.size()) {
    onig_region_clear(region);
    const int rc =
        onig_search(compiled_->re, str, end, str + last_end, end, region, ONIG_OPTION_NONE);
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

std::string oniguruma_version() { return onig_version(); }

std::string oniguruma_unicode_version() {
  // The library's run-time version (not the header's). From its release notes: 6.9.8 updated the
  // tables to Unicode 14.0, 6.9.9 to 15.1, 6.9.10 to 16.0.
  unsigned major = 0, minor = 0, teeny = 0;
  std::sscanf(onig_version(), "%u.%u.%u", &major, &minor, &teeny);
  const unsigned v = major * 10000 + minor * 100 + teeny;
  if (v >= 60910) return "16.0";
  if (v >= 60909) return "15.1";
  if (v >= 60908) return "14.0";
  return "13.0 or older";
}

}  // namespace tether::text
