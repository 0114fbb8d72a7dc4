// Tokenizer: loads tokenizer.json and runs the pipeline added tokens -> normalizer -> pre-tokenizer
// -> BPE -> truncation -> post-processor -> padding, in the Rust crate's order.
#include "text/tokenizer.h"

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <unordered_set>

#include "core/error.h"
#include "core/json_util.h"
#include "text/added_vocabulary.h"
#include "text/bpe.h"
#include "text/pipeline.h"
#include "text/sentencepiece_model.h"
#include "text/unicode.h"

namespace tether::text {

struct Truncation {
  std::size_t max_length = 0;
  bool left = false;  // direction "Left" keeps the end of the sequence
};

struct PaddingConfig {
  std::optional<std::size_t> fixed;  // nullopt: BatchLongest (a no-op on a single sequence)
  std::size_t multiple_of = 0;
  bool left = false;
  int32_t pad_id = 0;
};

struct TokenizerImpl {
  std::string where;
  std::unique_ptr<BpeModel> model;
  std::unique_ptr<Normalizer> normalizer;
  std::unique_ptr<PreTokenizer> pre_tokenizer;
  std::unique_ptr<PostProcessor> post_processor;
  std::unique_ptr<Decoder> decoder;
  std::unique_ptr<AddedVocabulary> added;
  std::optional<Truncation> truncation;
  std::optional<PaddingConfig> padding;
  int32_t vocab_size = 0;

  std::string normalize(std::string_view s) const {
    return normalizer ? normalizer->normalize(s) : std::string(s);
  }

  // Ids of `text` before truncation and post-processing.
  std::vector<int32_t> tokenize(std::string_view text) const {
    if (const std::size_t bad = find_invalid_utf8(text); bad != std::string_view::npos)
      throw Error(
          ErrorCode::invalid_argument,
          where + ": text to tokenize is not valid UTF-8 (byte " + std::to_string(bad) + ")");
    std::vector<Piece> pieces =
        added->extract_and_normalize(text, [this](std::string_view s) { return normalize(s); });
    if (pre_tokenizer) pre_tokenizer->pre_tokenize(pieces);
    std::vector<int32_t> ids;
    ids.reserve(text.size());
    for (const Piece& p : pieces) {
      if (p.id >= 0) {
        ids.push_back(p.id);
      } else {
        model->tokenize(p.text, ids);
      }
    }
    return ids;
  }

  int added_tokens(bool add_special_tokens) const {
    return add_special_tokens && post_processor ? post_processor->added_tokens_single() : 0;
  }

  // Truncates so the post-processed sequence fits `max_length`. Like the crate (built without
  // overflow checks), a limit below the number of added tokens wraps around and truncates nothing.
  void truncate(std::vector<int32_t>& ids, std::size_t max_length, bool left,
                bool add_special_tokens) const {
    const auto n_added = static_cast<std::size_t>(added_tokens(add_special_tokens));
    std::size_t limit = max_length;
    if (n_added > 0) {
      if (max_length < n_added) return;
      limit = max_length - n_added;
    }
    if (ids.size() <= limit) return;
    if (left) {
      ids.erase(ids.begin(), ids.end() - static_cast<std::ptrdiff_t>(limit));
    } else {
      ids.resize(limit);
    }
  }

  void post_process(std::vector<int32_t>& ids, bool add_special_tokens) const {
    if (post_processor) post_processor->process(ids, add_special_tokens);
  }
};

namespace {

AddedToken parse_added_token(const Json& j, const std::string& where) {
  if (!j.is_object()) throw Error(ErrorCode::format, where + " is not an object");
  AddedToken t;
  t.content = json_get<std::string>(j, "content", where);
  t.single_word = json_get_or<bool>(j, "single_word", false, where);
  t.lstrip = json_get_or<bool>(j, "lstrip", false, where);
  t.rstrip = json_get_or<bool>(j, "rstrip", false, where);
  t.normalized = json_get_or<bool>(j, "normalized", true, where);
  t.special = json_get_or<bool>(j, "special", false, where);
  return t;
}

std::optional<Truncation> parse_truncation(const Json& j, const std::string& where) {
  if (j.is_null()) return std::nullopt;
  if (!j.is_object()) throw Error(ErrorCode::format, where + " is not an object");
  Truncation t;
  t.max_length = json_get<std::size_t>(j, "max_length", where);
  const auto direction = json_get_or<std::string>(j, "direction", "Right", where);
  if (direction != "Left" && direction != "Right")
    throw Error(ErrorCode::format,
                where + ".direction '" + direction + "' is neither Left nor Right");
  t.left = direction == "Left";
  // Strategy and stride only matter for pairs and overflowing windows, which Tether does not
  // produce.
  return t;
}

std::optional<PaddingConfig> parse_padding(const Json& j, const std::string& where) {
  if (j.is_null()) return std::nullopt;
  if (!j.is_object()) throw Error(ErrorCode::format, where + " is not an object");
  PaddingConfig p;
  auto st = j.find("strategy");
  if (st == j.end()) throw Error(ErrorCode::not_found, where + ": missing field 'strategy'");
  if (st->is_string() && st->get<std::string>() == "BatchLongest") {
    p.fixed.reset();
  } else if (st->is_object() && st->contains("Fixed") && (*st)["Fixed"].is_number_unsigned()) {
    p.fixed = (*st)["Fixed"].get<std::size_t>();
  } else {
    throw Error(ErrorCode::format, where + ".strategy " + st->dump() +
                                       " is neither \"BatchLongest\" nor {\"Fixed\": n}");
  }
  const auto direction = json_get_or<std::string>(j, "direction", "Right", where);
  if (direction != "Left" && direction != "Right")
    throw Error(ErrorCode::format,
                where + ".direction '" + direction + "' is neither Left nor Right");
  p.left = direction == "Left";
  p.multiple_of = json_get_or<std::size_t>(j, "pad_to_multiple_of", 0, where);
  p.pad_id = json_get_or<int32_t>(j, "pad_id", 0, where);
  return p;
}

// How the pipeline deviates from the file (transformers class rebuilds, extra added tokens).
struct BuildOptions {
  // transformers classes whose constructor builds the pipeline around the file's vocabulary:
  // GPT2Tokenizer (ByteLevel only, BPE options reset) and GemmaTokenizer (SentencePiece-style BPE).
  // Qwen2Tokenizer (Qwen3-VL, so GR00T N1.7): NFC, Qwen2's split regex, ByteLevel without its own regex.
  enum class Rebuild { none, gpt2, gemma, qwen2 } rebuild = Rebuild::none;
  bool add_prefix_space = false;                 // GPT2Tokenizer's and Qwen2Tokenizer's ByteLevel option
  std::string unk_token;                         // GemmaTokenizer's BPE unk_token
  std::optional<std::vector<AddedToken>> added;  // replaces the file's added_tokens
  std::vector<AddedToken> extra;                 // registered after them
};

std::shared_ptr<TokenizerImpl> build(const Json& root, const std::string& where,
                                     const BuildOptions& opt = {}) {
  if (!root.is_object()) throw Error(ErrorCode::format, where + ": top level is not a JSON object");
  if (auto v = root.find("version"); v != root.end() && !v->is_null()) {
    if (!v->is_string() || v->get<std::string>() != "1.0")
      throw Error(ErrorCode::unsupported,
                  where + ": version " + v->dump() + " is not supported (expected \"1.0\")");
  }
  auto impl = std::make_shared<TokenizerImpl>();
  impl->where = where;
  auto field = [&](const char* key) -> const Json& {
    static const Json null_json;
    auto it = root.find(key);
    return it == root.end() ? null_json : *it;
  };
  const Json& model = field("model");
  if (model.is_null()) throw Error(ErrorCode::not_found, where + ": missing field 'model'");
  // The rebuilding classes keep only the file's vocabulary and merges.
  auto rebuilt_model = [&]() {
    Json rebuilt = Json::object();
    for (const char* key : {"type", "vocab", "merges"})
      if (model.is_object() && model.contains(key)) rebuilt[key] = model[key];
    return rebuilt;
  };
  if (opt.rebuild == BuildOptions::Rebuild::gpt2) {
    // The class builds BPE(vocab, merges) with default options and its own stages around it.
    impl->model = std::make_unique<BpeModel>(rebuilt_model(), where);
    const Json byte_level = {
        {"type", "ByteLevel"}, {"add_prefix_space", opt.add_prefix_space}, {"use_regex", true}};
    impl->pre_tokenizer = make_pre_tokenizer(byte_level, where + ": GPT2Tokenizer pre_tokenizer");
    impl->decoder = make_decoder(byte_level, where + ": GPT2Tokenizer decoder");
  } else if (opt.rebuild == BuildOptions::Rebuild::qwen2) {
    // Qwen2Tokenizer.__init__ (transformers 5.x): BPE(vocab, merges) with default options, NFC, a Split on the
    // class's pre-tokenize regex (isolated), ByteLevel(use_regex=False), ByteLevel decoder.
    impl->model = std::make_unique<BpeModel>(rebuilt_model(), where);
    impl->normalizer = make_normalizer({{"type", "NFC"}}, where + ": Qwen2Tokenizer normalizer");
    static const char* kQwen2Split =
        R"((?i:'s|'t|'re|'ve|'m|'ll|'d)|[^\r\n\p{L}\p{N}]?\p{L}+|\p{N}| ?[^\s\p{L}\p{N}]+[\r\n]*|\s*[\r\n]+|\s+(?!\S)|\s+)";
    const Json byte_level = {
        {"type", "ByteLevel"}, {"add_prefix_space", opt.add_prefix_space}, {"use_regex", false}};
    impl->pre_tokenizer = make_pre_tokenizer(
        {{"type", "Sequence"},
         {"pretokenizers", Json::array({Json{{"type", "Split"},
                                             {"pattern", {{"Regex", kQwen2Split}}},
                                             {"behavior", "Isolated"},
                                             {"invert", false}},
                                        byte_level})}},
        where + ": Qwen2Tokenizer pre_tokenizer");
    impl->decoder = make_decoder(byte_level, where + ": Qwen2Tokenizer decoder");
  } else if (opt.rebuild == BuildOptions::Rebuild::gemma) {
    // GemmaTokenizer.__init__ (transformers 5.x): BPE(vocab, merges, fuse_unk=True,
    // unk_token, byte_fallback=True), spaces replaced by U+2581 before a split on spaces (which so
    // finds none), and the SentencePiece decoder.
    Json bpe = rebuilt_model();
    bpe["fuse_unk"] = true;
    bpe["byte_fallback"] = true;
    bpe["unk_token"] = opt.unk_token;
    impl->model = std::make_unique<BpeModel>(bpe, where);
    const Json space = {{"String", " "}}, marker = {{"String", "\xE2\x96\x81"}};
    impl->normalizer =
        make_normalizer({{"type", "Replace"}, {"pattern", space}, {"content", "\xE2\x96\x81"}},
                        where + ": GemmaTokenizer normalizer");
    impl->pre_tokenizer = make_pre_tokenizer({{"type", "Split"},
                                              {"pattern", space},
                                              {"behavior", "MergedWithPrevious"},
                                              {"invert", false}},
                                             where + ": GemmaTokenizer pre_tokenizer");
    impl->decoder = make_decoder(
        {{"type", "Sequence"},
         {"decoders", Json::array({Json{{"type", "Replace"}, {"pattern", marker}, {"content", " "}},
                                   Json{{"type", "ByteFallback"}}, Json{{"type", "Fuse"}}})}},
        where + ": GemmaTokenizer decoder");
  } else {
    impl->model = std::make_unique<BpeModel>(model, where);
    impl->normalizer = make_normalizer(field("normalizer"), where + ": normalizer");
    impl->pre_tokenizer = make_pre_tokenizer(field("pre_tokenizer"), where + ": pre_tokenizer");
    impl->decoder = make_decoder(field("decoder"), where + ": decoder");
  }
  impl->post_processor = make_post_processor(field("post_processor"), where + ": post_processor");
  impl->truncation = parse_truncation(field("truncation"), where + ": truncation");
  impl->padding = parse_padding(field("padding"), where + ": padding");

  std::vector<AddedToken> tokens;
  const Json& added = field("added_tokens");
  if (opt.added) {
    tokens = *opt.added;
  } else if (!added.is_null()) {
    if (!added.is_array()) throw Error(ErrorCode::format, where + ": added_tokens is not an array");
    for (std::size_t k = 0; k < added.size(); ++k)
      tokens.push_back(
          parse_added_token(added[k], where + ": added_tokens[" + std::to_string(k) + "]"));
  }
  tokens.insert(tokens.end(), opt.extra.begin(), opt.extra.end());
  const TokenizerImpl* raw = impl.get();
  impl->added = std::make_unique<AddedVocabulary>(
      tokens, *impl->model, [raw](std::string_view s) { return raw->normalize(s); });

  std::unordered_set<std::string_view> distinct;
  for (const auto& [token, id] : impl->model->vocab()) distinct.insert(token);
  for (const auto& [token, id] : impl->added->contents()) distinct.insert(token);
  impl->vocab_size = static_cast<int32_t>(distinct.size());
  return impl;
}

}  // namespace

Tokenizer Tokenizer::from_file(const std::string& path) {
  return Tokenizer(build(read_json_file<Json>(path), path));
}

Tokenizer Tokenizer::from_json_string(std::string_view json, const std::string& where) {
  Json root = Json::parse(json, nullptr, /*allow_exceptions=*/false);
  if (root.is_discarded()) throw Error(ErrorCode::format, where + ": not valid JSON");
  return Tokenizer(build(root, where));
}

Tokenizer Tokenizer::from_transformers_dir(const std::string& dir) {
  return load_pretrained_tokenizer(dir).tokenizer;
}

namespace {

// A special-token entry of tokenizer_config.json: a string or an AddedToken dict.
std::optional<AddedToken> config_token(const Json& v, const std::string& where) {
  if (v.is_null()) return std::nullopt;
  AddedToken t;
  if (v.is_string()) {
    t.content = v.get<std::string>();
    t.special = true;
    t.normalized = false;
  } else if (v.is_object()) {
    t = parse_added_token(v, where);
    t.special = true;
  } else {
    throw Error(ErrorCode::format, where + " is neither a string nor an AddedToken object");
  }
  return t;
}

std::string side(const Json& config, const char* key, const char* fallback,
                 const std::string& where) {
  const auto v = json_get_or<std::string>(config, key, fallback, where);
  if (v != "left" && v != "right")
    throw Error(ErrorCode::format, where + ": " + key + " '" + v + "' is neither left nor right");
  return v;
}

// The tokenizer.json-shaped object transformers' GemmaTokenizer builds from a SentencePiece model
// (SentencePieceExtractor.extract in convert_slow_tokenizer.py): the pieces as the BPE vocabulary,
// merges from generate_merges, and the control and user-defined pieces as added tokens (control
// ones special), none of them normalized.
Json json_from_sentencepiece(const SentencePieceModel& m, std::vector<AddedToken>& added) {
  Json vocab = Json::object();
  for (std::size_t k = 0; k < m.pieces.size(); ++k) vocab[m.pieces[k].piece] = k;
  Json merges = Json::array();
  for (auto& [left, right] : generate_merges(m.pieces))
    merges.push_back(Json::array({std::move(left), std::move(right)}));
  for (const SentencePiece& p : m.pieces) {
    if (p.type != SentencePiece::control && p.type != SentencePiece::user_defined) continue;
    AddedToken t;
    t.content = p.piece;
    t.normalized = false;
    t.special = p.type == SentencePiece::control;
    added.push_back(std::move(t));
  }
  Json root = Json::object();
  root["version"] = "1.0";
  root["model"] = {{"type", "BPE"}, {"vocab", std::move(vocab)}, {"merges", std::move(merges)}};
  return root;
}

// transformers' update_post_processor: "[bos] $A [eos]" as add_bos_token / add_eos_token ask.
Json bos_eos_template(const std::optional<std::pair<std::string, int32_t>>& bos,
                      const std::optional<std::pair<std::string, int32_t>>& eos) {
  Json single = Json::array(), special = Json::object();
  auto add = [&](const std::pair<std::string, int32_t>& t) {
    single.push_back({{"SpecialToken", {{"id", t.first}, {"type_id", 0}}}});
    special[t.first] = {
        {"id", t.first}, {"ids", Json::array({t.second})}, {"tokens", Json::array({t.first})}};
  };
  if (bos) add(*bos);
  single.push_back({{"Sequence", {{"id", "A"}, {"type_id", 0}}}});
  if (eos) add(*eos);
  return {{"type", "TemplateProcessing"}, {"single", single}, {"special_tokens", special}};
}

}  // namespace

namespace {

// What load_pretrained_tokenizer builds, before it becomes a PretrainedTokenizer.
struct LoadedTokenizer {
  std::shared_ptr<TokenizerImpl> impl;
  std::string tokenizer_class;
  BatchOptions defaults;
  std::optional<int32_t> bos_token_id, eos_token_id, pad_token_id;
  std::string source;
};

// The files a tokenizer directory holds its vocabulary in, in the order transformers prefers them.
enum class VocabFiles {
  tokenizer_json,  // tokenizer.json
  sentencepiece,   // tokenizer.model
  vocab_merges,    // vocab.json + merges.txt, as Qwen2Tokenizer saves itself (GR00T N1.6's Eagle directory)
};

// vocab.json and merges.txt as the tokenizers crate reads them into a BPE model: "#version" lines
// skipped, every other line exactly two symbols separated by one space, ranked by line order.
Json json_from_vocab_merges(const std::string& vocab_path, const std::string& merges_path) {
  Json vocab = read_json_file<Json>(vocab_path);
  if (!vocab.is_object()) throw Error(ErrorCode::format, vocab_path + ": top level is not an object");
  std::ifstream in(merges_path, std::ios::binary);
  if (!in) throw Error(ErrorCode::not_found, merges_path + ": cannot be opened");
  Json merges = Json::array();
  std::string line;
  for (std::size_t number = 1; std::getline(in, line); ++number) {
    if (!line.empty() && line.back() == '\r') line.pop_back();
    if (line.rfind("#version", 0) == 0) continue;
    const std::size_t space = line.find(' ');
    if (space == std::string::npos || space == 0 || space + 1 == line.size() ||
        line.find(' ', space + 1) != std::string::npos)
      throw Error(ErrorCode::format, merges_path + ": line " + std::to_string(number) +
                                         " is not two symbols separated by one space");
    merges.push_back(Json::array({line.substr(0, space), line.substr(space + 1)}));
  }
  if (in.bad()) throw Error(ErrorCode::format, merges_path + ": read error");
  return Json{{"model", {{"type", "BPE"}, {"vocab", std::move(vocab)}, {"merges", std::move(merges)}}}};
}

// Where the vocabulary is: `path` is tokenizer.json, tokenizer.model or vocab.json (then with `merges_path`).
struct VocabSource {
  VocabFiles files;
  std::string path, merges_path;
};

// The tokenizer from `vocab`, with `config` standing for tokenizer_config.json (`config_path` names it in errors).
LoadedTokenizer load_tokenizer_files(const VocabSource& vocab, const Json& config, const std::string& config_path) {
  const VocabFiles files = vocab.files;
  const std::string& json_path = vocab.path;
  const std::string& model_path = vocab.path;
  const std::string& vocab_path = vocab.path;
  const bool has_json = files == VocabFiles::tokenizer_json;
  BuildOptions opt;
  std::string cls = json_get_or<std::string>(config, "tokenizer_class", "", config_path);
  std::string base = cls;
  if (base.size() > 4 && base.compare(base.size() - 4, 4, "Fast") == 0 &&
      base != "PreTrainedTokenizerFast")
    base.resize(base.size() - 4);
  const bool gemma = base == "GemmaTokenizer", qwen2 = base == "Qwen2Tokenizer";
  if (qwen2) {
    opt.rebuild = BuildOptions::Rebuild::qwen2;
    opt.add_prefix_space = json_get_or<bool>(config, "add_prefix_space", false, config_path);
  } else if (base == "GPT2Tokenizer") {
    opt.rebuild = BuildOptions::Rebuild::gpt2;
    opt.add_prefix_space = json_get_or<bool>(config, "add_prefix_space", false, config_path);
  } else if (gemma) {
    opt.rebuild = BuildOptions::Rebuild::gemma;
  } else if (!(base.empty() || base == "PreTrainedTokenizerFast" || base == "TokenizersBackend")) {
    throw Error(ErrorCode::unsupported,
                config_path + ": tokenizer_class '" + cls +
                    "' is not supported (transformers rebuilds it in a class-specific way)");
  }
  const std::string class_named =
      cls.empty() ? "no tokenizer_class in " + config_path : "tokenizer_class is '" + cls + "'";
  // Without tokenizer.json transformers converts tokenizer.model in a class-specific way; Tether
  // follows GemmaTokenizer's conversion only.
  if (files == VocabFiles::sentencepiece && !gemma)
    throw Error(ErrorCode::unsupported, model_path +
                                            ": a SentencePiece model without tokenizer.json is only supported for " +
                                            "tokenizer_class GemmaTokenizer (" + class_named + ")");
  // vocab.json + merges.txt go into the class's own pipeline; Tether knows Qwen2Tokenizer's. Its added tokens
  // come from added_tokens_decoder (transformers reads added_tokens.json only for configs without one).
  if (files == VocabFiles::vocab_merges) {
    if (!qwen2)
      throw Error(ErrorCode::unsupported, vocab_path + ": vocab.json and merges.txt without tokenizer.json are " +
                                              "only supported for tokenizer_class Qwen2Tokenizer (" + class_named +
                                              ")");
    if (auto it = config.find("added_tokens_decoder"); it == config.end() || it->is_null())
      throw Error(ErrorCode::unsupported, config_path + ": vocab.json and merges.txt without tokenizer.json need " +
                                              "added_tokens_decoder (the legacy added_tokens.json is not read)");
  }
  const std::string& source = vocab.path;
  std::vector<AddedToken> spm_added;
  const Json root = files == VocabFiles::tokenizer_json  ? read_json_file<Json>(json_path)
                    : files == VocabFiles::sentencepiece ? json_from_sentencepiece(read_sentencepiece_model(model_path),
                                                                                   spm_added)
                                                         : json_from_vocab_merges(vocab_path, vocab.merges_path);

  // Named special tokens: the config's, else the class defaults (GemmaTokenizer.__init__'s).
  std::vector<std::pair<std::string, AddedToken>> named;
  for (const char* key : {"bos_token", "eos_token", "unk_token", "sep_token", "pad_token",
                          "cls_token", "mask_token"}) {
    if (auto it = config.find(key); it != config.end()) {
      if (auto t = config_token(*it, config_path + ": " + key)) named.emplace_back(key, *t);
      continue;
    }
    if (qwen2) {  // Qwen2Tokenizer.__init__'s defaults: unk, eos and pad are all <|endoftext|>
      if (std::string(key) == "unk_token" || std::string(key) == "eos_token" || std::string(key) == "pad_token")
        named.emplace_back(key, *config_token(Json("<|endoftext|>"), key));
      continue;
    }
    if (!gemma) continue;
    static const std::pair<const char*, const char*> kGemmaDefaults[] = {{"bos_token", "<bos>"},
                                                                         {"eos_token", "<eos>"},
                                                                         {"unk_token", "<unk>"},
                                                                         {"pad_token", "<pad>"},
                                                                         {"mask_token", "<mask>"}};
    for (const auto& [k, content] : kGemmaDefaults)
      if (std::string(k) == key) named.emplace_back(key, *config_token(Json(content), key));
  }
  const std::size_t n_named = named.size();
  // transformers 5 reads additional_special_tokens as extra_special_tokens.
  auto extra_it = config.find("extra_special_tokens");
  std::string extra_key = "extra_special_tokens";
  if (extra_it == config.end() || extra_it->is_null()) {
    extra_it = config.find("additional_special_tokens");
    extra_key = "additional_special_tokens";
  }
  if (extra_it != config.end() && !extra_it->is_null()) {
    if (extra_it->is_array()) {
      for (std::size_t k = 0; k < extra_it->size(); ++k)
        if (auto t = config_token((*extra_it)[k],
                                  config_path + ": " + extra_key + "[" + std::to_string(k) + "]"))
          named.emplace_back("", *t);
    } else if (extra_it->is_object()) {
      for (auto e = extra_it->begin(); e != extra_it->end(); ++e)
        if (auto t = config_token(*e, config_path + ": " + extra_key + "." + e.key()))
          named.emplace_back("", *t);
    }
  }
  if (gemma) {
    opt.unk_token = "<unk>";
    for (std::size_t k = 0; k < n_named; ++k)
      if (named[k].first == "unk_token") opt.unk_token = named[k].second.content;
  }

  // Added tokens: the config's added_tokens_decoder when present (transformers prefers it), in id
  // order.
  std::vector<AddedToken> added;
  if (auto it = config.find("added_tokens_decoder"); it != config.end() && !it->is_null()) {
    if (!it->is_object())
      throw Error(ErrorCode::format, config_path + ": added_tokens_decoder is not an object");
    std::vector<std::pair<long, AddedToken>> by_id;
    for (auto e = it->begin(); e != it->end(); ++e) {
      long id = 0;
      try {
        id = std::stol(e.key());
      } catch (const std::exception&) {
        throw Error(ErrorCode::format,
                    config_path + ": added_tokens_decoder key '" + e.key() + "' is not an id");
      }
      by_id.emplace_back(
          id, parse_added_token(*e, config_path + ": added_tokens_decoder['" + e.key() + "']"));
    }
    std::stable_sort(by_id.begin(), by_id.end(),
                     [](const auto& a, const auto& b) { return a.first < b.first; });
    if (opt.rebuild != BuildOptions::Rebuild::none && has_json) {
      // The rebuilt backend starts without the file's added tokens and takes these instead.
      std::vector<AddedToken> list;
      for (auto& [id, t] : by_id) list.push_back(std::move(t));
      opt.added = std::move(list);
    } else {
      for (auto& [id, t] : by_id) added.push_back(std::move(t));
    }
  }
  if (files == VocabFiles::sentencepiece) {
    // The converted model's control and user-defined pieces, then the config's tokens. The named
    // and extra special tokens are registered again as special, which marks those pieces special.
    for (AddedToken& t : spm_added)
      for (const auto& [key, n] : named)
        if (n.content == t.content) t.special = true;
    opt.added = std::move(spm_added);
  }
  std::vector<std::string> known;
  auto remember = [&](const std::vector<AddedToken>& list) {
    for (const AddedToken& t : list) known.push_back(t.content);
  };
  if (opt.added) {
    remember(*opt.added);
  } else if (auto it = root.find("added_tokens"); it != root.end() && it->is_array()) {
    for (const Json& t : *it)
      if (t.is_object() && t.contains("content") && t["content"].is_string())
        known.push_back(t["content"].get<std::string>());
  }
  remember(added);
  opt.extra = std::move(added);
  for (const auto& [key, t] : named) {
    if (std::find(known.begin(), known.end(), t.content) == known.end()) {
      opt.extra.push_back(t);
      known.push_back(t.content);
    }
  }

  std::shared_ptr<TokenizerImpl> impl = build(root, source, opt);
  auto id_of = [&](const char* key) -> std::optional<int32_t> {
    for (std::size_t k = 0; k < n_named; ++k) {
      if (named[k].first != key) continue;
      const std::string& content = named[k].second.content;
      if (auto id = impl->added->token_to_id(content)) return id;
      return impl->model->token_to_id(content);
    }
    return std::nullopt;
  };
  if (!has_json) {
    // No post-processor in any file: transformers builds one from add_bos_token / add_eos_token
    // (both false when absent). With tokenizer.json it drops those flags and keeps the file's.
    auto flagged = [&](const char* flag,
                       const char* key) -> std::optional<std::pair<std::string, int32_t>> {
      if (!json_get_or<bool>(config, flag, false, config_path)) return std::nullopt;
      for (std::size_t k = 0; k < n_named; ++k)
        if (named[k].first == key)
          if (auto id = id_of(key)) return std::make_pair(named[k].second.content, *id);
      return std::nullopt;  // no such token: transformers turns the flag off
    };
    impl->post_processor =
        make_post_processor(bos_eos_template(flagged("add_bos_token", "bos_token"),
                                             flagged("add_eos_token", "eos_token")),
                            config_path + ": add_bos_token/add_eos_token template");
  }

  LoadedTokenizer out{impl, cls, BatchOptions{}, std::nullopt, std::nullopt, std::nullopt, source};
  out.defaults.truncate_right = side(config, "truncation_side", "right", config_path) == "right";
  // GemmaTokenizer's class attribute is padding_side = "left"; the base class's is "right".
  out.defaults.pad_right =
      side(config, "padding_side", gemma ? "left" : "right", config_path) == "right";
  out.bos_token_id = id_of("bos_token");
  out.eos_token_id = id_of("eos_token");
  out.pad_token_id = id_of("pad_token");
  if (out.pad_token_id) out.defaults.pad_token_id = *out.pad_token_id;
  return out;
}

}  // namespace

PretrainedTokenizer load_pretrained_tokenizer(const std::string& dir) {
  namespace fs = std::filesystem;
  const std::string config_path = dir + "/tokenizer_config.json";
  std::error_code ec;
  auto present = [&](const char* name) { return fs::exists(dir + "/" + name, ec); };
  VocabSource vocab;
  if (present("tokenizer.json")) {
    vocab = {VocabFiles::tokenizer_json, dir + "/tokenizer.json", ""};
  } else if (present("tokenizer.model")) {
    vocab = {VocabFiles::sentencepiece, dir + "/tokenizer.model", ""};
  } else if (present("vocab.json") && present("merges.txt")) {
    vocab = {VocabFiles::vocab_merges, dir + "/vocab.json", dir + "/merges.txt"};
  } else {
    throw Error(ErrorCode::not_found, dir + ": no tokenizer.json or tokenizer.model (nor vocab.json with merges.txt; " +
                                          dir + "/tokenizer.json not found)");
  }
  Json config = Json::object();
  if (fs::exists(config_path, ec)) config = read_json_file<Json>(config_path);
  if (!config.is_object())
    throw Error(ErrorCode::format, config_path + ": top level is not an object");
  LoadedTokenizer t = load_tokenizer_files(vocab, config, config_path);
  return {Tokenizer(t.impl), t.tokenizer_class, t.defaults, t.bos_token_id, t.eos_token_id, t.pad_token_id, t.source};
}

PretrainedTokenizer load_gemma_sentencepiece(const std::string& model_path) {
  std::error_code ec;
  if (!std::filesystem::exists(model_path, ec)) throw Error(ErrorCode::not_found, model_path + ": not found");
  const Json config = {{"tokenizer_class", "GemmaTokenizer"}};
  LoadedTokenizer t = load_tokenizer_files({VocabFiles::sentencepiece, model_path, ""}, config,
                                           model_path + " (read as a GemmaTokenizer without tokenizer_config.json)");
  return {Tokenizer(t.impl), t.tokenizer_class, t.defaults, t.bos_token_id, t.eos_token_id, t.pad_token_id, t.source};
}

std::vector<int32_t> Tokenizer::encode(std::string_view text, bool add_special_tokens) const {
  const TokenizerImpl& t = *impl_;
  std::vector<int32_t> ids = t.tokenize(text);
  if (t.truncation)
    t.truncate(ids, t.truncation->max_length, t.truncation->left, add_special_tokens);
  t.post_process(ids, add_special_tokens);
  if (t.padding && t.padding->fixed) {
    std::size_t target = *t.padding->fixed;
    if (t.padding->multiple_of > 0 && target % t.padding->multiple_of != 0)
      target += t.padding->multiple_of - target % t.padding->multiple_of;
    if (ids.size() < target) {
      const auto n = static_cast<std::ptrdiff_t>(target - ids.size());
      ids.insert(t.padding->left ? ids.begin() : ids.end(), static_cast<std::size_t>(n),
                 t.padding->pad_id);
    }
  } else if (t.padding && t.padding->multiple_of > 0 && ids.size() % t.padding->multiple_of != 0) {
    const std::size_t target =
        ids.size() + t.padding->multiple_of - ids.size() % t.padding->multiple_of;
    ids.insert(t.padding->left ? ids.begin() : ids.end(), target - ids.size(), t.padding->pad_id);
  }
  return ids;
}

std::string Tokenizer::decode(const std::vector<int32_t>& ids, bool skip_special_tokens) const {
  const TokenizerImpl& t = *impl_;
  std::vector<std::string> tokens;
  tokens.reserve(ids.size());
  for (int32_t id : ids) {
    const std::string* token = nullptr;
    if (const AddedToken* a = t.added->token_for_id(id)) {
      token = &a->content;
    } else {
      token = t.model->id_to_token(id);
    }
    if (!token) continue;
    if (skip_special_tokens && t.added->is_special(*token)) continue;
    tokens.push_back(*token);
  }
  if (t.decoder) return t.decoder->decode(std::move(tokens));
  std::string out;
  for (std::size_t k = 0; k < tokens.size(); ++k) {
    if (k) out += ' ';
    out += tokens[k];
  }
  return out;
}

std::optional<int32_t> Tokenizer::token_to_id(std::string_view token) const {
  if (auto id = impl_->added->token_to_id(token)) return id;
  return impl_->model->token_to_id(token);
}

std::optional<std::string> Tokenizer::id_to_token(int32_t id) const {
  if (const AddedToken* a = impl_->added->token_for_id(id)) return a->content;
  if (const std::string* s = impl_->model->id_to_token(id)) return *s;
  return std::nullopt;
}

int32_t Tokenizer::vocab_size() const { return impl_->vocab_size; }

int Tokenizer::num_special_tokens_to_add() const { return impl_->added_tokens(true); }

BatchEncoding encode_batch(const Tokenizer& tokenizer, const std::vector<std::string>& texts,
                           const BatchOptions& options, bool add_special_tokens) {
  const TokenizerImpl& t = *tokenizer.impl_;
  if (options.max_length < 0)
    throw Error(ErrorCode::invalid_argument, "encode_batch: max_length is negative");
  if (options.padding == Padding::max_length && options.max_length == 0)
    throw Error(ErrorCode::invalid_argument,
                "encode_batch: padding max_length needs max_length > 0");
  std::vector<std::vector<int32_t>> rows;
  rows.reserve(texts.size());
  std::size_t longest = 0;
  for (const std::string& text : texts) {
    std::vector<int32_t> ids = t.tokenize(text);
    if (options.truncation && options.max_length > 0)
      t.truncate(ids, static_cast<std::size_t>(options.max_length), !options.truncate_right,
                 add_special_tokens);
    t.post_process(ids, add_special_tokens);
    longest = std::max(longest, ids.size());
    rows.push_back(std::move(ids));
  }
  std::size_t length = longest;
  if (options.padding == Padding::max_length)
    length = std::max(longest, static_cast<std::size_t>(options.max_length));
  for (std::size_t r = 0; r < rows.size(); ++r) {
    if (rows[r].size() != length && (options.padding == Padding::none || rows[r].size() > length))
      throw Error(ErrorCode::invalid_argument,
                  "encode_batch: row " + std::to_string(r) + " has " +
                      std::to_string(rows[r].size()) + " tokens but the batch is " +
                      std::to_string(length) + " long and padding cannot equalise it");
  }
  if (options.padding == Padding::max_length &&
      longest > static_cast<std::size_t>(options.max_length)) {
    for (std::size_t r = 0; r < rows.size(); ++r) {
      if (rows[r].size() != longest)
        throw Error(
            ErrorCode::invalid_argument,
            "encode_batch: rows longer than max_length (truncation off) leave a ragged batch");
    }
  }
  BatchEncoding out;
  out.batch = static_cast<int64_t>(rows.size());
  out.length = static_cast<int64_t>(length);
  out.ids.assign(rows.size() * length, options.pad_token_id);
  out.mask.assign(rows.size() * length, 0);
  for (std::size_t r = 0; r < rows.size(); ++r) {
    const std::size_t pad = length - rows[r].size();
    const std::size_t offset = r * length + (options.pad_right ? 0 : pad);
    for (std::size_t k = 0; k < rows[r].size(); ++k) {
      out.ids[offset + k] = rows[r][k];
      out.mask[offset + k] = 1;
    }
  }
  return out;
}

}  // namespace tether::text
