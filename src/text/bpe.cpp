// BPE model: loading from tokenizer.json and the priority-queue merge loop (O(n log n) per word).
#include "text/bpe.h"

#include <mutex>
#include <queue>

#include "core/error.h"
#include "text/unicode.h"

namespace tether::text {

namespace {

std::string byte_token(unsigned b) {
  static const char* hex = "0123456789ABCDEF";
  std::string s = "<0x";
  s += hex[b >> 4];
  s += hex[b & 15];
  s += '>';
  return s;
}

}  // namespace

BpeModel::BpeModel(const Json& j, const std::string& where) : where_(where) {
  const std::string w = where + ": model";
  if (!j.is_object()) throw Error(ErrorCode::format, w + " is not an object");
  const auto type = json_get_or<std::string>(j, "type", "BPE", w);
  if (type != "BPE")
    throw Error(ErrorCode::unsupported, w + ".type '" + type + "' is not supported (only BPE)");
  if (auto it = j.find("dropout"); it != j.end() && !it->is_null()) {
    if (!it->is_number()) throw Error(ErrorCode::format, w + ".dropout is not a number");
    if (it->get<double>() != 0.0)
      throw Error(ErrorCode::unsupported, w + ".dropout " + it->dump() + " is not supported");
  }
  if (auto it = j.find("unk_token"); it != j.end() && !it->is_null())
    unk_token_ = json_get<std::string>(j, "unk_token", w);
  continuing_subword_prefix_ = json_get_or<std::string>(j, "continuing_subword_prefix", "", w);
  end_of_word_suffix_ = json_get_or<std::string>(j, "end_of_word_suffix", "", w);
  fuse_unk_ = json_get_or<bool>(j, "fuse_unk", false, w);
  byte_fallback_ = json_get_or<bool>(j, "byte_fallback", false, w);
  ignore_merges_ = json_get_or<bool>(j, "ignore_merges", false, w);

  auto vit = j.find("vocab");
  if (vit == j.end() || vit->is_null())
    throw Error(ErrorCode::not_found, w + ": missing field 'vocab'");
  if (!vit->is_object())
    throw Error(ErrorCode::format, w + ".vocab is not an object of token -> id");
  vocab_.reserve(vit->size());
  for (auto it = vit->begin(); it != vit->end(); ++it) {
    if (!it->is_number_integer() || it->get<int64_t>() < 0 || it->get<int64_t>() > INT32_MAX)
      throw Error(ErrorCode::format,
                  w + ".vocab['" + it.key() + "'] is not a valid id (" + it->dump() + ")");
    const auto id = static_cast<int32_t>(it->get<int64_t>());
    vocab_.emplace(it.key(), id);
    vocab_r_.emplace(id, it.key());
  }

  auto mit = j.find("merges");
  if (mit == j.end() || mit->is_null())
    throw Error(ErrorCode::not_found, w + ": missing field 'merges'");
  if (!mit->is_array()) throw Error(ErrorCode::format, w + ".merges is not an array");
  merges_.reserve(mit->size());
  uint32_t rank = 0;
  for (std::size_t k = 0; k < mit->size(); ++k) {
    const Json& m = (*mit)[k];
    const std::string mw = w + ".merges[" + std::to_string(k) + "]";
    std::string a, b;
    if (m.is_string()) {
      // Legacy "a b" form: exactly one space; "#version" header lines are skipped.
      const std::string s = m.get<std::string>();
      if (s.rfind("#version", 0) == 0) continue;
      const std::size_t sp = s.find(' ');
      if (sp == std::string::npos || s.find(' ', sp + 1) != std::string::npos)
        throw Error(ErrorCode::format,
                    mw + " '" + s + "' is not two tokens separated by one space");
      a = s.substr(0, sp);
      b = s.substr(sp + 1);
    } else if (m.is_array() && m.size() == 2 && m[0].is_string() && m[1].is_string()) {
      a = m[0].get<std::string>();
      b = m[1].get<std::string>();
    } else {
      throw Error(ErrorCode::format, mw + " is neither \"a b\" nor [a, b] (" + m.dump() + ")");
    }
    auto ia = vocab_.find(a), ib = vocab_.find(b);
    if (ia == vocab_.end())
      throw Error(ErrorCode::format, mw + ": token '" + a + "' is not in the vocabulary");
    if (ib == vocab_.end())
      throw Error(ErrorCode::format, mw + ": token '" + b + "' is not in the vocabulary");
    const std::size_t plen = continuing_subword_prefix_.size();
    if (b.size() < plen)
      throw Error(ErrorCode::format, mw + ": token '" + b + "' is shorter than the subword prefix");
    const std::string merged = a + b.substr(plen);
    auto im = vocab_.find(merged);
    if (im == vocab_.end())
      throw Error(ErrorCode::format,
                  mw + ": merged token '" + merged + "' is not in the vocabulary");
    // A repeated pair takes the later rank, as building the crate's hash map does.
    merges_[pair_key(ia->second, ib->second)] = Merge{rank, im->second};
    ++rank;
  }

  for (unsigned byte = 0; byte < 256; ++byte) {
    auto it = vocab_.find(byte_token(byte));
    byte_ids_[byte] = it == vocab_.end() ? -1 : it->second;
  }
}

std::optional<int32_t> BpeModel::token_to_id(std::string_view token) const {
  auto it = vocab_.find(token);
  if (it == vocab_.end()) return std::nullopt;
  return it->second;
}

const std::string* BpeModel::id_to_token(int32_t id) const {
  auto it = vocab_r_.find(id);
  return it == vocab_r_.end() ? nullptr : &it->second;
}

void BpeModel::tokenize(std::string_view piece, std::vector<int32_t>& out) const {
  if (piece.empty()) return;
  if (ignore_merges_) {
    if (auto it = vocab_.find(piece); it != vocab_.end()) {
      out.push_back(it->second);
      return;
    }
  }
  {
    std::shared_lock lock(cache_mutex_);
    if (auto it = cache_.find(piece); it != cache_.end()) {
      out.insert(out.end(), it->second.begin(), it->second.end());
      return;
    }
  }
  std::vector<int32_t> ids;
  merge_word(piece, ids);
  out.insert(out.end(), ids.begin(), ids.end());
  if (piece.size() < kCacheMaxBytes) {
    std::unique_lock lock(cache_mutex_);
    if (cache_.size() < kCacheCapacity) cache_.emplace(std::string(piece), std::move(ids));
  }
}

void BpeModel::merge_word(std::string_view word, std::vector<int32_t>& out) const {
  struct Symbol {
    int32_t c;
    int64_t prev, next;
    std::size_t len;  // bytes covered; 0 marks a symbol merged into its left neighbour
  };
  std::vector<Symbol> symbols;
  symbols.reserve(word.size());
  auto add = [&](int32_t c, std::size_t len) {
    const auto n = static_cast<int64_t>(symbols.size());
    if (!symbols.empty()) symbols.back().next = n;
    symbols.push_back(Symbol{c, n - 1, -1, len});
  };

  // Pending run of unknown characters: emitted when a known token follows, or at the end.
  bool unk_pending = false;
  int32_t unk_id_pending = 0;
  std::size_t unk_len = 0;
  auto unk_id = [&]() {
    auto it = vocab_.find(*unk_token_);
    if (it == vocab_.end())
      throw Error(ErrorCode::format,
                  where_ + ": model.unk_token '" + *unk_token_ + "' is not in the vocabulary");
    return it->second;
  };

  std::string s;
  std::size_t i = 0;
  while (i < word.size()) {
    const std::size_t n = utf8_len(static_cast<unsigned char>(word[i]));
    const bool is_first = i == 0, is_last = i + n >= word.size();
    s.assign(word.substr(i, n));
    i += n;
    if (!is_first && !continuing_subword_prefix_.empty()) s = continuing_subword_prefix_ + s;
    if (is_last && !end_of_word_suffix_.empty()) s += end_of_word_suffix_;

    if (auto it = vocab_.find(s); it != vocab_.end()) {
      if (unk_pending) {
        add(unk_id_pending, unk_len);
        unk_pending = false;
      }
      add(it->second, n);
      continue;
    }
    if (byte_fallback_) {
      bool all = true;
      for (char b : s) all = all && byte_ids_[static_cast<unsigned char>(b)] >= 0;
      if (all) {
        // A pending unknown run stays pending past these bytes: the crate emits it later.
        for (char b : s) add(byte_ids_[static_cast<unsigned char>(b)], 1);
        continue;
      }
    }
    if (unk_token_) {
      if (unk_pending && fuse_unk_) {
        unk_len += n;
      } else {
        if (unk_pending) add(unk_id_pending, unk_len);
        unk_pending = true;
        unk_id_pending = unk_id();
        unk_len = n;
      }
    }
    // Without an unk_token an unknown character is dropped, as in the crate.
  }
  if (unk_pending) add(unk_id_pending, unk_len);

  struct Candidate {
    uint32_t rank;
    std::size_t pos;
    int32_t new_id;
    bool operator>(const Candidate& o) const {
      return rank != o.rank ? rank > o.rank : pos > o.pos;
    }
  };
  std::priority_queue<Candidate, std::vector<Candidate>, std::greater<Candidate>> queue;
  for (std::size_t k = 0; k + 1 < symbols.size(); ++k) {
    if (auto it = merges_.find(pair_key(symbols[k].c, symbols[k + 1].c)); it != merges_.end())
      queue.push(Candidate{it->second.rank, k, it->second.new_id});
  }
  const auto count = static_cast<int64_t>(symbols.size());
  while (!queue.empty()) {
    const Candidate top = queue.top();
    queue.pop();
    Symbol& left = symbols[top.pos];
    if (left.len == 0 || left.next == -1) continue;
    const auto next_pos = static_cast<std::size_t>(left.next);
    const Symbol right = symbols[next_pos];
    // Stale entries: the pair must still exist and still produce the same token.
    auto it = merges_.find(pair_key(left.c, right.c));
    if (it == merges_.end() || it->second.new_id != top.new_id) continue;

    left.c = top.new_id;
    left.len += right.len;
    left.next = right.next;
    symbols[next_pos].len = 0;
    if (right.next > -1 && right.next < count)
      symbols[static_cast<std::size_t>(right.next)].prev = int64_t(top.pos);

    const Symbol current = symbols[top.pos];
    if (current.prev >= 0) {
      const auto prev = static_cast<std::size_t>(current.prev);
      if (auto m = merges_.find(pair_key(symbols[prev].c, current.c)); m != merges_.end())
        queue.push(Candidate{m->second.rank, prev, m->second.new_id});
    }
    if (current.next >= 0 && current.next < count) {
      if (auto m =
              merges_.find(pair_key(current.c, symbols[static_cast<std::size_t>(current.next)].c));
          m != merges_.end())
        queue.push(Candidate{m->second.rank, top.pos, m->second.new_id});
    }
  }
  for (const Symbol& sym : symbols)
    if (sym.len != 0) out.push_back(sym.c);
}

}  // namespace tether::text
