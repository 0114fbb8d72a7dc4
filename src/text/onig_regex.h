// Tokenizer patterns (tokenizer.json's Split / Replace regexes and the GPT-2 pattern) on
// Oniguruma, the engine the Rust `tokenizers` crate compiles them with, iterated the way the onig
// crate's find_iter does.
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

// The linked Oniguruma's version ("6.9.8") and the Unicode version of its property tables
// ("14.0"), which decide how characters of later Unicode versions are classified.
std::string oniguruma_version();
std::string oniguruma_unicode_version();

}  // namespace tether::text
