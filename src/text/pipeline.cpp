// Normalizers, pre-tokenizers, post-processors and decoders of tokenizer.json, with the Rust
// crate's splitting semantics (Pattern matches + SplitDelimiterBehavior) reproduced on plain
// strings.
#include "text/pipeline.h"

#include <algorithm>
#include <array>
#include <functional>

#include "core/error.h"
#include "text/onig_regex.h"
#include "text/unicode.h"

namespace tether::text {

namespace {

// ---- byte-level table -------------------------------------------------------------------------

struct ByteTable {
  std::array<std::string, 256> to_char;
  std::array<int16_t, 512> from_char;  // code points used are all below 512
  ByteTable() {
    from_char.fill(-1);
    int n = 0;
    for (int b = 0; b < 256; ++b) {
      const bool printable =
          (b >= '!' && b <= '~') || (b >= 0xA1 && b <= 0xAC) || (b >= 0xAE && b <= 0xFF);
      const char32_t c = printable ? char32_t(b) : char32_t(256 + n++);
      append_utf8(to_char[static_cast<std::size_t>(b)], c);
      from_char[c] = static_cast<int16_t>(b);
    }
  }
};

const ByteTable& byte_table() {
  static const ByteTable table;
  return table;
}

// ---- shared splitting ---------------------------------------------------------------------------

struct Span {
  std::size_t begin, end;
  bool is_match;
};

std::vector<Span> regex_spans(const OnigRegex& re, std::string_view s) {
  if (s.empty()) return {Span{0, 0, false}};
  std::vector<Span> out;
  std::size_t prev = 0;
  for (auto [b, e] : re.find_all(s)) {
    if (prev != b) out.push_back(Span{prev, b, false});
    out.push_back(Span{b, e, true});
    prev = e;
  }
  if (prev != s.size()) out.push_back(Span{prev, s.size(), false});
  return out;
}

std::vector<Span> char_spans(std::string_view s, const std::function<bool(char32_t)>& pred) {
  if (s.empty()) return {Span{0, 0, false}};
  std::vector<Span> out;
  std::size_t last_offset = 0, i = 0;
  while (i < s.size()) {
    std::size_t n;
    const char32_t c = decode_utf8(s, i, n);
    if (pred(c)) {
      if (last_offset < i) out.push_back(Span{last_offset, i, false});
      out.push_back(Span{i, i + n, true});
      last_offset = i + n;
    }
    i += n;
  }
  if (s.size() > last_offset) out.push_back(Span{last_offset, s.size(), false});
  return out;
}

enum class Behavior { removed, isolated, merged_with_previous, merged_with_next, contiguous };

Behavior parse_behavior(const std::string& name, const std::string& where) {
  if (name == "Removed") return Behavior::removed;
  if (name == "Isolated") return Behavior::isolated;
  if (name == "MergedWithPrevious") return Behavior::merged_with_previous;
  if (name == "MergedWithNext") return Behavior::merged_with_next;
  if (name == "Contiguous") return Behavior::contiguous;
  throw Error(ErrorCode::unsupported, where + ".behavior '" + name + "' is not supported");
}

// Appends the non-empty parts of `s` cut according to `behavior`.
void split_by(std::string_view s, const std::vector<Span>& spans, Behavior behavior,
              std::vector<std::string>& out) {
  struct Part {
    std::size_t begin, end;
    bool remove;
  };
  std::vector<Part> parts;
  parts.reserve(spans.size());
  bool previous_match = false;
  switch (behavior) {
    case Behavior::isolated:
      for (const Span& sp : spans) parts.push_back(Part{sp.begin, sp.end, false});
      break;
    case Behavior::removed:
      for (const Span& sp : spans) parts.push_back(Part{sp.begin, sp.end, sp.is_match});
      break;
    case Behavior::contiguous:
      for (const Span& sp : spans) {
        if (sp.is_match == previous_match && !parts.empty()) {
          parts.back().end = sp.end;
        } else {
          parts.push_back(Part{sp.begin, sp.end, false});
        }
        previous_match = sp.is_match;
      }
      break;
    case Behavior::merged_with_previous:
      for (const Span& sp : spans) {
        if (sp.is_match && !previous_match && !parts.empty()) {
          parts.back().end = sp.end;
        } else {
          parts.push_back(Part{sp.begin, sp.end, false});
        }
        previous_match = sp.is_match;
      }
      break;
    case Behavior::merged_with_next:
      for (auto it = spans.rbegin(); it != spans.rend(); ++it) {
        if (it->is_match && !previous_match && !parts.empty()) {
          parts.back().begin = it->begin;
        } else {
          parts.push_back(Part{it->begin, it->end, false});
        }
        previous_match = it->is_match;
      }
      std::reverse(parts.begin(), parts.end());
      break;
  }
  for (const Part& p : parts)
    if (!p.remove && p.end > p.begin) out.emplace_back(s.substr(p.begin, p.end - p.begin));
}

// Replaces each text piece by the pieces `fn` cuts it into; added-token pieces pass through.
template <typename Fn>
void split_pieces(std::vector<Piece>& pieces, Fn&& fn) {
  std::vector<Piece> out;
  out.reserve(pieces.size() * 2);
  std::vector<std::string> parts;
  for (Piece& p : pieces) {
    if (p.id >= 0) {
      out.push_back(std::move(p));
      continue;
    }
    parts.clear();
    fn(p.text, parts);
    for (std::string& s : parts)
      if (!s.empty()) out.push_back(Piece{std::move(s), -1});
  }
  pieces = std::move(out);
}

std::string type_of(const Json& j, const std::string& where) {
  if (!j.is_object()) throw Error(ErrorCode::format, where + " is not an object");
  return json_get<std::string>(j, "type", where);
}

const Json& array_field(const Json& j, const std::string& key, const std::string& where) {
  auto it = j.find(key);
  if (it == j.end() || it->is_null())
    throw Error(ErrorCode::not_found, where + ": missing field '" + key + "'");
  if (!it->is_array()) throw Error(ErrorCode::format, where + "." + key + " is not an array");
  return *it;
}

// {"String": "..."} or {"Regex": "..."}, the crate's pattern object.
OnigRegex make_pattern(const Json& j, const std::string& where) {
  auto it = j.find("pattern");
  if (it == j.end() || !it->is_object() || it->size() != 1)
    throw Error(ErrorCode::format,
                where + ".pattern must be {\"String\": ...} or {\"Regex\": ...}");
  if (auto s = it->find("String"); s != it->end() && s->is_string())
    return OnigRegex::literal(s->get<std::string>(), where + ".pattern");
  if (auto r = it->find("Regex"); r != it->end() && r->is_string())
    return OnigRegex(r->get<std::string>(), where + ".pattern");
  throw Error(ErrorCode::format, where + ".pattern must be {\"String\": ...} or {\"Regex\": ...}");
}

// ---- normalizers ------------------------------------------------------------------------------

class SequenceNormalizer final : public Normalizer {
 public:
  explicit SequenceNormalizer(std::vector<std::unique_ptr<Normalizer>> parts)
      : parts_(std::move(parts)) {}
  std::string normalize(std::string_view s) const override {
    std::string cur(s);
    for (const auto& n : parts_) cur = n->normalize(cur);
    return cur;
  }

 private:
  std::vector<std::unique_ptr<Normalizer>> parts_;
};

class UnicodeNormalizer final : public Normalizer {
 public:
  explicit UnicodeNormalizer(NormalForm form) : form_(form) {}
  std::string normalize(std::string_view s) const override { return text::normalize(s, form_); }

 private:
  NormalForm form_;
};

class LowercaseNormalizer final : public Normalizer {
 public:
  std::string normalize(std::string_view s) const override { return lowercase(s); }
};

class PrependNormalizer final : public Normalizer {
 public:
  explicit PrependNormalizer(std::string prefix) : prefix_(std::move(prefix)) {}
  std::string normalize(std::string_view s) const override {
    if (s.empty()) return {};
    return prefix_ + std::string(s);
  }

 private:
  std::string prefix_;
};

class ReplaceNormalizer final : public Normalizer {
 public:
  ReplaceNormalizer(OnigRegex re, std::string content)
      : re_(std::move(re)), content_(std::move(content)) {}
  std::string normalize(std::string_view s) const override {
    if (s.empty()) return {};
    std::string out;
    std::size_t last = 0;
    for (auto [b, e] : re_.find_all(s)) {
      out.append(s.substr(last, b - last));
      out += content_;
      last = e;
    }
    out.append(s.substr(last));
    return out;
  }

 private:
  OnigRegex re_;
  std::string content_;
};

class StripNormalizer final : public Normalizer {
 public:
  StripNormalizer(bool left, bool right) : left_(left), right_(right) {}
  std::string normalize(std::string_view s) const override {
    std::size_t b = 0, e = s.size();
    if (left_) {
      while (b < e) {
        std::size_t n;
        if (!is_white_space(decode_utf8(s, b, n))) break;
        b += n;
      }
    }
    if (right_) {
      while (e > b) {
        std::size_t start = e - 1;
        while (start > b && (static_cast<unsigned char>(s[start]) & 0xC0) == 0x80) --start;
        std::size_t n;
        if (!is_white_space(decode_utf8(s, start, n))) break;
        e = start;
      }
    }
    return std::string(s.substr(b, e - b));
  }

 private:
  bool left_, right_;
};

// ---- pre-tokenizers ---------------------------------------------------------------------------

class SequencePreTokenizer final : public PreTokenizer {
 public:
  explicit SequencePreTokenizer(std::vector<std::unique_ptr<PreTokenizer>> parts)
      : parts_(std::move(parts)) {}
  void pre_tokenize(std::vector<Piece>& pieces) const override {
    for (const auto& p : parts_) p->pre_tokenize(pieces);
  }

 private:
  std::vector<std::unique_ptr<PreTokenizer>> parts_;
};

constexpr const char* kGpt2Pattern =
    R"('s|'t|'re|'ve|'m|'ll|'d| ?\p{L}+| ?\p{N}+| ?[^\s\p{L}\p{N}]+|\s+(?!\S)|\s+)";

class ByteLevelPreTokenizer final : public PreTokenizer {
 public:
  ByteLevelPreTokenizer(bool add_prefix_space, bool use_regex, const std::string& where)
      : add_prefix_space_(add_prefix_space), use_regex_(use_regex) {
    if (use_regex_) re_ = std::make_unique<OnigRegex>(kGpt2Pattern, where + " (GPT-2 pattern)");
  }
  void pre_tokenize(std::vector<Piece>& pieces) const override {
    split_pieces(pieces, [&](const std::string& text, std::vector<std::string>& out) {
      std::string s = add_prefix_space_ && (text.empty() || text[0] != ' ') ? " " + text : text;
      if (use_regex_) {
        split_by(s, regex_spans(*re_, s), Behavior::isolated, out);
      } else {
        out.push_back(std::move(s));
      }
    });
    const ByteTable& table = byte_table();
    for (Piece& p : pieces) {
      if (p.id >= 0) continue;
      std::string mapped;
      mapped.reserve(p.text.size() * 2);
      for (char c : p.text) mapped += table.to_char[static_cast<unsigned char>(c)];
      p.text = std::move(mapped);
    }
  }

 private:
  bool add_prefix_space_, use_regex_;
  std::unique_ptr<OnigRegex> re_;
};

class SplitPreTokenizer final : public PreTokenizer {
 public:
  SplitPreTokenizer(OnigRegex re, Behavior behavior, bool invert)
      : re_(std::move(re)), behavior_(behavior), invert_(invert) {}
  void pre_tokenize(std::vector<Piece>& pieces) const override {
    split_pieces(pieces, [&](const std::string& text, std::vector<std::string>& out) {
      std::vector<Span> spans = regex_spans(re_, text);
      if (invert_)
        for (Span& sp : spans) sp.is_match = !sp.is_match;
      split_by(text, spans, behavior_, out);
    });
  }

 private:
  OnigRegex re_;
  Behavior behavior_;
  bool invert_;
};

class DigitsPreTokenizer final : public PreTokenizer {
 public:
  explicit DigitsPreTokenizer(bool individual) : individual_(individual) {}
  void pre_tokenize(std::vector<Piece>& pieces) const override {
    split_pieces(pieces, [&](const std::string& text, std::vector<std::string>& out) {
      split_by(text, char_spans(text, is_numeric),
               individual_ ? Behavior::isolated : Behavior::contiguous, out);
    });
  }

 private:
  bool individual_;
};

// ---- post-processors --------------------------------------------------------------------------

class ByteLevelPostProcessor final : public PostProcessor {
 public:
  int added_tokens_single() const override { return 0; }
  void process(std::vector<int32_t>&, bool) const override {
  }  // only trims offsets, which Tether does not return
};

class TemplatePostProcessor final : public PostProcessor {
 public:
  TemplatePostProcessor(const Json& j, const std::string& where) {
    const Json& single = array_field(j, "single", where);
    auto st = j.find("special_tokens");
    for (std::size_t k = 0; k < single.size(); ++k) {
      const Json& piece = single[k];
      const std::string pw = where + ".single[" + std::to_string(k) + "]";
      if (!piece.is_object() || piece.size() != 1)
        throw Error(ErrorCode::format, pw + " is not a template piece");
      if (auto seq = piece.find("Sequence"); seq != piece.end()) {
        if (json_get<std::string>(*seq, "id", pw + ".Sequence") != "A")
          throw Error(ErrorCode::format,
                      pw + ": a single-sequence template can only use sequence A");
        items_.push_back(Item{true, {}});
      } else if (auto sp = piece.find("SpecialToken"); sp != piece.end()) {
        const auto name = json_get<std::string>(*sp, "id", pw + ".SpecialToken");
        if (st == j.end() || !st->is_object() || !st->contains(name))
          throw Error(ErrorCode::format, pw + ": special token '" + name + "' is missing from " +
                                             where + ".special_tokens");
        const Json& def = (*st)[name];
        Item item{false, {}};
        for (const Json& id : array_field(def, "ids", where + ".special_tokens['" + name + "']")) {
          if (!id.is_number_integer())
            throw Error(ErrorCode::format, where + ".special_tokens['" + name + "'].ids");
          item.ids.push_back(id.get<int32_t>());
        }
        added_ += static_cast<int>(item.ids.size());
        items_.push_back(std::move(item));
      } else {
        throw Error(ErrorCode::format, pw + " is neither Sequence nor SpecialToken");
      }
    }
  }
  int added_tokens_single() const override { return added_; }
  void process(std::vector<int32_t>& ids, bool add_special_tokens) const override {
    std::vector<int32_t> out;
    out.reserve(ids.size() + static_cast<std::size_t>(added_));
    for (const Item& item : items_) {
      if (item.is_sequence) {
        out.insert(out.end(), ids.begin(), ids.end());
      } else if (add_special_tokens) {
        out.insert(out.end(), item.ids.begin(), item.ids.end());
      }
    }
    ids = std::move(out);
  }

 private:
  struct Item {
    bool is_sequence;
    std::vector<int32_t> ids;
  };
  std::vector<Item> items_;
  int added_ = 0;
};

class SequencePostProcessor final : public PostProcessor {
 public:
  explicit SequencePostProcessor(std::vector<std::unique_ptr<PostProcessor>> parts)
      : parts_(std::move(parts)) {}
  int added_tokens_single() const override {
    int n = 0;
    for (const auto& p : parts_) n += p->added_tokens_single();
    return n;
  }
  void process(std::vector<int32_t>& ids, bool add_special_tokens) const override {
    for (const auto& p : parts_) p->process(ids, add_special_tokens);
  }

 private:
  std::vector<std::unique_ptr<PostProcessor>> parts_;
};

// ---- decoders ---------------------------------------------------------------------------------

class ByteLevelDecoder final : public Decoder {
 public:
  std::vector<std::string> decode_chain(std::vector<std::string> tokens) const override {
    const ByteTable& table = byte_table();
    std::string bytes;
    std::string token_bytes;
    for (const std::string& t : tokens) {
      // A token with any character outside the table contributes its raw UTF-8 instead.
      token_bytes.clear();
      bool all = true;
      std::size_t i = 0;
      while (i < t.size()) {
        std::size_t n;
        const char32_t c = decode_utf8(t, i, n);
        i += n;
        const int b = c < 512 ? table.from_char[c] : -1;
        if (b < 0) {
          all = false;
          break;
        }
        token_bytes.push_back(static_cast<char>(b));
      }
      bytes += all ? token_bytes : t;
    }
    return {utf8_lossy(bytes)};
  }
};

class SequenceDecoder final : public Decoder {
 public:
  explicit SequenceDecoder(std::vector<std::unique_ptr<Decoder>> parts)
      : parts_(std::move(parts)) {}
  std::vector<std::string> decode_chain(std::vector<std::string> tokens) const override {
    for (const auto& d : parts_) tokens = d->decode_chain(std::move(tokens));
    return tokens;
  }

 private:
  std::vector<std::unique_ptr<Decoder>> parts_;
};

// Each token with the pattern's matches replaced (SentencePiece's "\u2581" back to a space).
class ReplaceDecoder final : public Decoder {
 public:
  ReplaceDecoder(OnigRegex re, std::string content)
      : re_(std::move(re)), content_(std::move(content)) {}
  std::vector<std::string> decode_chain(std::vector<std::string> tokens) const override {
    for (std::string& t : tokens) {
      std::string out;
      std::size_t last = 0;
      for (auto [b, e] : re_.find_all(t)) {
        out.append(t, last, b - last);
        out += content_;
        last = e;
      }
      out.append(t, last, std::string::npos);
      t = std::move(out);
    }
    return tokens;
  }

 private:
  OnigRegex re_;
  std::string content_;
};

// Runs of "<0xHH>" tokens become the text of their bytes, or one U+FFFD per byte when those bytes
// are not valid UTF-8, as the crate's ByteFallback decoder does.
class ByteFallbackDecoder final : public Decoder {
 public:
  std::vector<std::string> decode_chain(std::vector<std::string> tokens) const override {
    std::vector<std::string> out;
    out.reserve(tokens.size());
    std::string bytes;
    auto flush = [&] {
      if (bytes.empty()) return;
      if (find_invalid_utf8(bytes) == std::string_view::npos) {
        out.push_back(bytes);
      } else {
        for (std::size_t k = 0; k < bytes.size(); ++k) out.emplace_back("\xEF\xBF\xBD");
      }
      bytes.clear();
    };
    for (std::string& t : tokens) {
      if (const int b = byte_of(t); b >= 0) {
        bytes.push_back(static_cast<char>(b));
        continue;
      }
      flush();
      out.push_back(std::move(t));
    }
    flush();
    return out;
  }

 private:
  static int hex(char c) {
    if (c >= '0' && c <= '9') return c - '0';
    if (c >= 'a' && c <= 'f') return c - 'a' + 10;
    if (c >= 'A' && c <= 'F') return c - 'A' + 10;
    return -1;
  }
  // u8::from_str_radix(&token[3..5], 16) on a six-byte "<0x..>" token; -1 when it is not one.
  static int byte_of(const std::string& t) {
    if (t.size() != 6 || t.compare(0, 3, "<0x") != 0 || t[5] != '>') return -1;
    const int hi = hex(t[3]), lo = hex(t[4]);
    if (t[3] == '+' && lo >= 0) return lo;  // Rust's parser accepts a leading '+'
    return hi >= 0 && lo >= 0 ? hi * 16 + lo : -1;
  }
};

// All tokens joined into one.
class FuseDecoder final : public Decoder {
 public:
  std::vector<std::string> decode_chain(std::vector<std::string> tokens) const override {
    std::string out;
    for (const std::string& t : tokens) out += t;
    return {out};
  }
};

// Up to `start` leading and `stop` trailing occurrences of one character removed from each token.
class StripDecoder final : public Decoder {
 public:
  StripDecoder(std::string content, std::size_t start, std::size_t stop)
      : content_(std::move(content)), start_(start), stop_(stop) {}
  std::vector<std::string> decode_chain(std::vector<std::string> tokens) const override {
    for (std::string& t : tokens) {
      std::vector<std::size_t> offsets;  // start of each character, then the end
      for (std::size_t i = 0; i < t.size(); i += utf8_len(static_cast<unsigned char>(t[i])))
        offsets.push_back(i);
      const std::size_t n = offsets.size();
      offsets.push_back(t.size());
      auto is_content = [&](std::size_t k) {
        return t.compare(offsets[k], offsets[k + 1] - offsets[k], content_) == 0;
      };
      std::size_t first = 0, last = n;
      for (std::size_t k = 0; k < std::min(start_, n) && is_content(k); ++k) first = k + 1;
      for (std::size_t k = 0; k < std::min(stop_, n) && is_content(n - 1 - k); ++k)
        last = n - 1 - k;
      t = first < last ? t.substr(offsets[first], offsets[last] - offsets[first]) : std::string();
    }
    return tokens;
  }

 private:
  std::string content_;
  std::size_t start_, stop_;
};

}  // namespace

const std::string& byte_to_unicode(unsigned char b) { return byte_table().to_char[b]; }

int byte_from_unicode(char32_t c) { return c < 512 ? byte_table().from_char[c] : -1; }

std::unique_ptr<Normalizer> make_normalizer(const Json& j, const std::string& where) {
  if (j.is_null()) return nullptr;
  const std::string type = type_of(j, where);
  if (type == "Sequence") {
    const Json& list = array_field(j, "normalizers", where);
    std::vector<std::unique_ptr<Normalizer>> parts;
    for (std::size_t k = 0; k < list.size(); ++k) {
      const std::string w = where + ".normalizers[" + std::to_string(k) + "]";
      if (list[k].is_null()) throw Error(ErrorCode::format, w + " is null");
      parts.push_back(make_normalizer(list[k], w));
    }
    return std::make_unique<SequenceNormalizer>(std::move(parts));
  }
  if (type == "NFC") return std::make_unique<UnicodeNormalizer>(NormalForm::nfc);
  if (type == "NFD") return std::make_unique<UnicodeNormalizer>(NormalForm::nfd);
  if (type == "NFKC") return std::make_unique<UnicodeNormalizer>(NormalForm::nfkc);
  if (type == "NFKD") return std::make_unique<UnicodeNormalizer>(NormalForm::nfkd);
  if (type == "Lowercase") return std::make_unique<LowercaseNormalizer>();
  if (type == "Prepend")
    return std::make_unique<PrependNormalizer>(json_get<std::string>(j, "prepend", where));
  if (type == "Replace")
    return std::make_unique<ReplaceNormalizer>(make_pattern(j, where),
                                               json_get<std::string>(j, "content", where));
  if (type == "Strip")
    return std::make_unique<StripNormalizer>(json_get<bool>(j, "strip_left", where),
                                             json_get<bool>(j, "strip_right", where));
  throw Error(ErrorCode::unsupported, where + ": normalizer type '" + type + "' is not supported");
}

std::unique_ptr<PreTokenizer> make_pre_tokenizer(const Json& j, const std::string& where) {
  if (j.is_null()) return nullptr;
  const std::string type = type_of(j, where);
  if (type == "Sequence") {
    const Json& list = array_field(j, "pretokenizers", where);
    std::vector<std::unique_ptr<PreTokenizer>> parts;
    for (std::size_t k = 0; k < list.size(); ++k) {
      const std::string w = where + ".pretokenizers[" + std::to_string(k) + "]";
      if (list[k].is_null()) throw Error(ErrorCode::format, w + " is null");
      parts.push_back(make_pre_tokenizer(list[k], w));
    }
    return std::make_unique<SequencePreTokenizer>(std::move(parts));
  }
  if (type == "ByteLevel")
    return std::make_unique<ByteLevelPreTokenizer>(
        json_get_or<bool>(j, "add_prefix_space", true, where),
        json_get_or<bool>(j, "use_regex", true, where), where);
  if (type == "Split")
    return std::make_unique<SplitPreTokenizer>(
        make_pattern(j, where), parse_behavior(json_get<std::string>(j, "behavior", where), where),
        json_get<bool>(j, "invert", where));
  if (type == "Digits")
    return std::make_unique<DigitsPreTokenizer>(
        json_get_or<bool>(j, "individual_digits", false, where));
  throw Error(ErrorCode::unsupported,
              where + ": pre-tokenizer type '" + type + "' is not supported");
}

std::unique_ptr<PostProcessor> make_post_processor(const Json& j, const std::string& where) {
  if (j.is_null()) return nullptr;
  const std::string type = type_of(j, where);
  if (type == "ByteLevel") return std::make_unique<ByteLevelPostProcessor>();
  if (type == "TemplateProcessing") return std::make_unique<TemplatePostProcessor>(j, where);
  if (type == "Sequence") {
    const Json& list = array_field(j, "processors", where);
    std::vector<std::unique_ptr<PostProcessor>> parts;
    for (std::size_t k = 0; k < list.size(); ++k) {
      const std::string w = where + ".processors[" + std::to_string(k) + "]";
      if (list[k].is_null()) throw Error(ErrorCode::format, w + " is null");
      parts.push_back(make_post_processor(list[k], w));
    }
    return std::make_unique<SequencePostProcessor>(std::move(parts));
  }
  throw Error(ErrorCode::unsupported,
              where + ": post-processor type '" + type + "' is not supported");
}

std::string Decoder::decode(std::vector<std::string> tokens) const {
  std::string out;
  for (const std::string& t : decode_chain(std::move(tokens))) out += t;
  return out;
}

std::unique_ptr<Decoder> make_decoder(const Json& j, const std::string& where) {
  if (j.is_null()) return nullptr;
  const std::string type = type_of(j, where);
  if (type == "ByteLevel") return std::make_unique<ByteLevelDecoder>();
  if (type == "Sequence") {
    const Json& list = array_field(j, "decoders", where);
    std::vector<std::unique_ptr<Decoder>> parts;
    for (std::size_t k = 0; k < list.size(); ++k) {
      const std::string w = where + ".decoders[" + std::to_string(k) + "]";
      if (list[k].is_null()) throw Error(ErrorCode::format, w + " is null");
      parts.push_back(make_decoder(list[k], w));
    }
    return std::make_unique<SequenceDecoder>(std::move(parts));
  }
  if (type == "Replace")
    return std::make_unique<ReplaceDecoder>(make_pattern(j, where),
                                            json_get<std::string>(j, "content", where));
  if (type == "ByteFallback") return std::make_unique<ByteFallbackDecoder>();
  if (type == "Fuse") return std::make_unique<FuseDecoder>();
  if (type == "Strip") {
    const auto content = json_get<std::string>(j, "content", where);
    std::size_t n = 0;
    if (content.empty() || find_invalid_utf8(content) != std::string_view::npos ||
        (decode_utf8(content, 0, n), n != content.size()))
      throw Error(ErrorCode::format, where + ".content must be a single character");
    return std::make_unique<StripDecoder>(content, json_get<std::size_t>(j, "start", where),
                                          json_get<std::size_t>(j, "stop", where));
  }
  throw Error(ErrorCode::unsupported, where + ": decoder type '" + type + "' is not supported");
}

}  // namespace tether::text
