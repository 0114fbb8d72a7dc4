// The BPE model of a tokenizer.json: vocabulary, ranked merges, unknown/byte-fallback handling and
// a bounded word cache. Merging follows the Rust crate's priority order exactly (lowest rank, then
// leftmost position), so ids match even when several merges produce the same token.
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <shared_mutex>
#include <string>
#include <string_view>
#include <unordered_map>
#include <vector>

#include "core/json_util.h"

namespace tether::text {

// Tokenizer files are read unordered: their key order carries no meaning and their vocabularies are large.
using Json = JsonMap;

struct StringHash {
  using is_transparent = void;
  std::size_t operator()(std::string_view s) const { return std::hash<std::string_view>{}(s); }
};
using Vocab = std::unordered_map<std::string, int32_t, StringHash, std::equal_to<>>;

class BpeModel {
 public:
  // `j` is the "model" object; `where` names the file for errors.
  BpeModel(const Json& j, const std::string& where);

  // Appends the ids for one pre-tokenized piece.
  void tokenize(std::string_view piece, std::vector<int32_t>& out) const;

  std::optional<int32_t> token_to_id(std::string_view token) const;
  const std::string* id_to_token(int32_t id) const;
  const Vocab& vocab() const { return vocab_; }
  std::size_t vocab_size() const { return vocab_.size(); }

 private:
  void merge_word(std::string_view word, std::vector<int32_t>& out) const;

  struct Merge {
    uint32_t rank;
    int32_t new_id;
  };
  static uint64_t pair_key(int32_t a, int32_t b) {
    return (uint64_t(uint32_t(a)) << 32) | uint32_t(b);
  }

  std::string where_;
  Vocab vocab_;
  std::unordered_map<int32_t, std::string> vocab_r_;
  std::unordered_map<uint64_t, Merge> merges_;
  std::optional<std::string> unk_token_;
  std::string continuing_subword_prefix_, end_of_word_suffix_;
  bool fuse_unk_ = false, byte_fallback_ = false, ignore_merges_ = false;
  int32_t byte_ids_[256];  // id of "<0xHH>" or -1, for byte_fallback

  // Results for pieces shorter than kCacheMaxBytes; stops growing at kCacheCapacity entries.
  static constexpr std::size_t kCacheCapacity = 10000, kCacheMaxBytes = 256;
  mutable std::shared_mutex cache_mutex_;
  mutable std::unordered_map<std::string, std::vector<int32_t>, StringHash, std::equal_to<>> cache_;
};

}  // namespace tether::text
