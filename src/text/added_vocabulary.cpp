// Added-token registration (id assignment) and the input split on added tokens.
#include "text/added_vocabulary.h"

#include <algorithm>

#include "text/unicode.h"

namespace tether::text {

namespace {

bool same_token(const AddedToken& a, const AddedToken& b) {
  return a.content == b.content && a.single_word == b.single_word && a.lstrip == b.lstrip &&
         a.rstrip == b.rstrip && a.normalized == b.normalized && a.special == b.special;
}

// Index of the last character's first byte in the non-empty valid UTF-8 `s`.
std::size_t last_char_start(std::string_view s) {
  std::size_t i = s.size() - 1;
  while (i > 0 && (static_cast<unsigned char>(s[i]) & 0xC0) == 0x80) --i;
  return i;
}

bool ends_with_word(std::string_view s) {
  if (s.empty()) return false;
  std::size_t n;
  return is_rust_regex_word(decode_utf8(s, last_char_start(s), n));
}

bool starts_with_word(std::string_view s) {
  if (s.empty()) return false;
  std::size_t n;
  return is_rust_regex_word(decode_utf8(s, 0, n));
}

// Start of the run of white space that ends `s` (s.size() when there is none).
std::size_t trailing_space_start(std::string_view s) {
  std::size_t end = s.size();
  while (end > 0) {
    const std::size_t start = last_char_start(s.substr(0, end));
    std::size_t n;
    if (!is_white_space(decode_utf8(s, start, n))) break;
    end = start;
  }
  return end;
}

// Length in bytes of the run of white space that starts `s`.
std::size_t leading_space_len(std::string_view s) {
  std::size_t i = 0;
  while (i < s.size()) {
    std::size_t n;
    if (!is_white_space(decode_utf8(s, i, n))) break;
    i += n;
  }
  return i;
}

}  // namespace

void AddedVocabulary::Trie::insert(std::string_view pattern, int32_t id) {
  if (pattern.empty()) return;  // an empty pattern would match everywhere; no real file has one
  first_byte[static_cast<unsigned char>(pattern[0])] = true;
  int32_t node = 0;
  for (char ch : pattern) {
    const auto b = static_cast<unsigned char>(ch);
    auto& next = nodes[static_cast<std::size_t>(node)].next;
    auto it = std::find_if(next.begin(), next.end(), [b](const auto& e) { return e.first == b; });
    if (it != next.end()) {
      node = it->second;
    } else {
      const auto child = static_cast<int32_t>(nodes.size());
      next.emplace_back(b, child);
      nodes.emplace_back();
      node = child;
    }
  }
  // With duplicate patterns the first one registered is reported, as in aho-corasick.
  if (nodes[static_cast<std::size_t>(node)].id < 0) nodes[static_cast<std::size_t>(node)].id = id;
}

void AddedVocabulary::Trie::find(std::string_view text, std::size_t from, std::size_t& start,
                                 std::size_t& end, int32_t& id) const {
  start = std::string_view::npos;
  for (std::size_t p = from; p < text.size(); ++p) {
    if (!first_byte[static_cast<unsigned char>(text[p])]) continue;
    int32_t node = 0;
    for (std::size_t q = p; q < text.size(); ++q) {
      const auto b = static_cast<unsigned char>(text[q]);
      const auto& next = nodes[static_cast<std::size_t>(node)].next;
      auto it = std::find_if(next.begin(), next.end(), [b](const auto& e) { return e.first == b; });
      if (it == next.end()) break;
      node = it->second;
      if (nodes[static_cast<std::size_t>(node)].id >= 0) {
        start = p;
        end = q + 1;
        id = nodes[static_cast<std::size_t>(node)].id;
      }
    }
    if (start != std::string_view::npos) return;
  }
}

AddedVocabulary::AddedVocabulary(const std::vector<AddedToken>& tokens, const BpeModel& model,
                                 const std::function<std::string(std::string_view)>& normalize) {
  std::vector<AddedToken> specials, classic, existing;
  for (const AddedToken& t : tokens) {
    if (t.special && !t.content.empty() && special_set_.insert(t.content).second)
      specials.push_back(t);
  }
  int32_t next_id = static_cast<int32_t>(model.vocab_size());
  for (const AddedToken& t : tokens) {
    if (t.content.empty() || std::any_of(existing.begin(), existing.end(),
                                         [&](const AddedToken& e) { return same_token(e, t); }))
      continue;
    int32_t id;
    if (auto known = token_to_id(t.content)) {
      id = *known;
    } else if (auto in_model = model.token_to_id(t.content)) {
      id = *in_model;
    } else {
      id = next_id++;
    }
    by_content_[t.content] = id;
    by_id_[id] = t;
    if (!special_set_.count(t.content)) classic.push_back(t);
    existing.push_back(t);
  }
  auto id_of = [&](const std::string& content) {
    if (auto a = token_to_id(content)) return *a;
    return *model.token_to_id(content);
  };
  for (const auto* list : {&specials, &classic}) {
    for (const AddedToken& t : *list) {
      if (t.normalized) {
        normalized_trie_.insert(normalize(t.content), id_of(t.content));
      } else {
        raw_trie_.insert(t.content, id_of(t.content));
      }
    }
  }
}

std::optional<int32_t> AddedVocabulary::token_to_id(std::string_view content) const {
  auto it = by_content_.find(std::string(content));
  if (it == by_content_.end()) return std::nullopt;
  return it->second;
}

const AddedToken* AddedVocabulary::token_for_id(int32_t id) const {
  auto it = by_id_.find(id);
  return it == by_id_.end() ? nullptr : &it->second;
}

void AddedVocabulary::split_on(const Trie& trie, std::string_view text,
                               std::vector<Piece>& out) const {
  auto emit = [&](std::size_t b, std::size_t e, int32_t id) {
    if (e > b) out.push_back(Piece{std::string(text.substr(b, e - b)), id});
  };
  if (trie.empty()) {
    emit(0, text.size(), -1);
    return;
  }
  std::size_t start_offset = 0, search = 0;
  while (search < text.size()) {
    std::size_t start, stop;
    int32_t id;
    trie.find(text, search, start, stop, id);
    if (start == std::string_view::npos) break;
    search = stop;  // the matcher resumes after the match itself, whatever stripping does below
    const AddedToken& tok = by_id_.at(id);
    if (tok.single_word) {
      const bool start_space = start == 0 || !ends_with_word(text.substr(0, start));
      const bool stop_space = stop == text.size() || !starts_with_word(text.substr(stop));
      if (!start_space || !stop_space) continue;
    }
    if (tok.lstrip) start = std::max(trailing_space_start(text.substr(0, start)), start_offset);
    if (tok.rstrip) stop += leading_space_len(text.substr(stop));
    if (start_offset < start) emit(start_offset, start, -1);
    emit(start, stop, id);
    start_offset = stop;
  }
  if (start_offset < text.size()) emit(start_offset, text.size(), -1);
}

std::vector<Piece> AddedVocabulary::extract_and_normalize(
    std::string_view text, const std::function<std::string(std::string_view)>& normalize) const {
  std::vector<Piece> raw;
  split_on(raw_trie_, text, raw);
  std::vector<Piece> out;
  out.reserve(raw.size());
  for (Piece& p : raw) {
    if (p.id >= 0) {
      out.push_back(std::move(p));
      continue;
    }
    split_on(normalized_trie_, normalize(p.text), out);
  }
  return out;
}

}  // namespace tether::text
