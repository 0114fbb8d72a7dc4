// Added tokens (special or not) and the first tokenization stage: cutting the input on them, before
// and after normalisation, with the single_word / lstrip / rstrip rules of the Rust crate.
#pragma once

#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <string_view>
#include <unordered_map>
#include <unordered_set>
#include <vector>

#include "text/bpe.h"

namespace tether::text {

struct AddedToken {
  std::string content;
  bool single_word = false, lstrip = false, rstrip = false, normalized = true, special = false;
};

// A piece of the input on its way through the pipeline: either an added token already resolved
// to its id, or text still to be normalised / pre-tokenized / run through the model.
struct Piece {
  std::string text;
  int32_t id = -1;
};

class AddedVocabulary {
 public:
  // Registers `tokens` the way the crate does when reading tokenizer.json: ids come from the model
  // vocabulary when the content is there, else are numbered from the model's vocabulary size.
  // `normalize` maps the content of normalized tokens to the form they are matched in.
  AddedVocabulary(const std::vector<AddedToken>& tokens, const BpeModel& model,
                  const std::function<std::string(std::string_view)>& normalize);

  // Splits `text` on added tokens; non-token pieces come back normalised by `normalize`.
  std::vector<Piece> extract_and_normalize(
      std::string_view text, const std::function<std::string(std::string_view)>& normalize) const;

  std::optional<int32_t> token_to_id(std::string_view content) const;
  const AddedToken* token_for_id(int32_t id) const;
  bool is_special(std::string_view content) const {
    return special_set_.count(std::string(content)) != 0;
  }
  const std::unordered_map<std::string, int32_t>& contents() const { return by_content_; }

 private:
  // Byte trie answering "longest pattern starting here", giving Aho-Corasick leftmost-longest
  // matches when scanned left to right.
  struct Trie {
    struct Node {
      std::vector<std::pair<unsigned char, int32_t>> next;
      int32_t id = -1;  // token id when a pattern ends here
    };
    std::vector<Node> nodes{Node{}};
    bool first_byte[256] = {};
    bool empty() const { return nodes.size() == 1; }
    void insert(std::string_view pattern, int32_t id);
    // Leftmost match at or after `from`: {start, end, id}; start == npos when none.
    void find(std::string_view text, std::size_t from, std::size_t& start, std::size_t& end,
              int32_t& id) const;
  };

  void split_on(const Trie& trie, std::string_view text, std::vector<Piece>& out) const;

  std::unordered_map<std::string, int32_t> by_content_;
  std::unordered_map<int32_t, AddedToken> by_id_;
  std::unordered_set<std::string> special_set_;
  Trie raw_trie_, normalized_trie_;
};

}  // namespace tether::text
