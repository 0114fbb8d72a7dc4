// Regexes written for Oniguruma (what the Rust `tokenizers` crate compiles tokenizer.json patterns
// with) run on PCRE2: the pattern is translated where the two dialects differ, and iteration
// reproduces the onig crate's handling of empty matches.
#pragma once

#include <cstddef>
#include <memory>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

namespace tether::text {

class OnigRegex {
 public:
  // `where` names the pattern's origin for errors (file and field).
  OnigRegex(const std::string& onig_pattern, const std::string& where);
  // A pattern matching `literal` exactly (the crate escapes String patterns into a regex).
  static OnigRegex literal(std::string_view literal, const std::string& where);
  ~OnigRegex();
  OnigRegex(OnigRegex&&) noexcept;
  OnigRegex& operator=(OnigRegex&&) noexcept;

  // All non-overlapping matches as [begin, end) byte offsets, in order. `text` must be valid UTF-8.
  std::vector<std::pair<std::size_t, std::size_t>> find_all(std::string_view text) const;

 private:
  struct Compiled;
  std::unique_ptr<Compiled> compiled_;
};

// Which engine regexes compiled from now on use (measurement only; Oniguruma by default).
enum class RegexEngine { oniguruma, pcre2 };
namespace detail {
void set_regex_engine(RegexEngine engine);
RegexEngine regex_engine();
}  // namespace detail

// Exposed for tests: the PCRE2 pattern a given Oniguruma pattern becomes.
std::string translate_onig_pattern(std::string_view pattern, const std::string& where);

}  // namespace tether::text
