// BPE tokenizer loaded from a Hugging Face `tokenizer.json` (byte-level or SentencePiece-style with
// byte fallback), reproducing the Rust `tokenizers` package id for id, plus transformers-style
// class rebuilds, SentencePiece-model conversion and batch padding/truncation.
#pragma once

#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

namespace tether::text {

struct TokenizerImpl;
struct BatchOptions;
struct BatchEncoding;
struct PretrainedTokenizer;

class Tokenizer {
 public:
  // Errors name the file and the JSON field at fault; components Tether does not implement are
  // rejected here with ErrorCode::unsupported rather than silently tokenizing differently.
  static Tokenizer from_file(const std::string& tokenizer_json_path);
  // A checkpoint directory loaded the way transformers 5.x does it; see load_pretrained_tokenizer.
  static Tokenizer from_transformers_dir(const std::string& dir);
  // `where` names the source in error messages (normally the file path).
  static Tokenizer from_json_string(std::string_view json, const std::string& where);

  // Throws ErrorCode::invalid_argument (naming the tokenizer's file) when `text` is not valid
  // UTF-8. Applies the truncation and padding settings stored in the file, as
  // `tokenizers.Tokenizer.encode` does.
  std::vector<int32_t> encode(std::string_view text, bool add_special_tokens = true) const;
  // Ids unknown to the vocabulary are skipped, as the Rust crate does.
  std::string decode(const std::vector<int32_t>& ids, bool skip_special_tokens = false) const;

  std::optional<int32_t> token_to_id(std::string_view token) const;
  std::optional<std::string> id_to_token(int32_t id) const;
  int32_t vocab_size() const;  // distinct token strings, model vocabulary plus added tokens
  // How many ids the post-processor adds around a single sequence (e.g. 1 for a BOS template).
  int num_special_tokens_to_add() const;

 private:
  explicit Tokenizer(std::shared_ptr<const TokenizerImpl> impl) : impl_(std::move(impl)) {}
  std::shared_ptr<const TokenizerImpl> impl_;  // immutable after load; copies share it

  friend PretrainedTokenizer load_pretrained_tokenizer(const std::string&);
  friend PretrainedTokenizer load_gemma_sentencepiece(const std::string&);
  friend BatchEncoding encode_batch(const Tokenizer&, const std::vector<std::string>&,
                                    const BatchOptions&, bool);
};

enum class Padding { none, longest, max_length };

struct BatchOptions {
  Padding padding = Padding::longest;
  int max_length = 0;      // 0: no limit (truncation off, and padding max_length is an error)
  bool truncation = true;  // truncate each sequence, special tokens included, to max_length
  bool truncate_right =
      true;               // transformers truncation_side="right" (SmolVLM's config says "left")
  bool pad_right = true;  // transformers padding_side="right"
  int32_t pad_token_id = 0;
};

// Row-major [batch, length] ids and attention mask (1 = token, 0 = padding).
struct BatchEncoding {
  int64_t batch = 0, length = 0;
  std::vector<int64_t> ids;
  std::vector<uint8_t> mask;
};

// Same result as calling a transformers PreTrainedTokenizerFast with padding=..., max_length=...,
// truncation=..., padding_side=...: the text's tokens are cut from the right so the sequence with
// its post-processor tokens fits max_length, then rows are padded. The file's own truncation and
// padding settings are ignored here, as transformers overrides them. Throws invalid_argument when
// rows would be ragged (padding none or max_length without truncation, with unequal lengths).
BatchEncoding encode_batch(const Tokenizer& tokenizer, const std::vector<std::string>& texts,
                           const BatchOptions& options, bool add_special_tokens = true);

// A checkpoint's tokenizer as transformers 5.x AutoTokenizer builds it from <dir>/tokenizer.json
// (or, without it, <dir>/tokenizer.model) and <dir>/tokenizer_config.json, which is not always what
// tokenizer.json alone describes:
//  - tokenizer_class "GPT2Tokenizer" (SmolVLM, SmolLM2) rebuilds the pipeline: the file's
//    normalizer and pre-tokenizer are dropped for ByteLevel(add_prefix_space from the config) — so
//    no Digits split — and the BPE options reset; vocabulary, merges, added tokens and
//    post-processor stay.
//  - "GemmaTokenizer" (PaliGemma, so pi0 / pi0.5) rebuilds it too: BPE with byte_fallback,
//    fuse_unk and the config's unk_token, normalizer Replace(" " -> U+2581), pre-tokenizer
//    Split(" ", MergedWithPrevious), decoder Replace/ByteFallback/Fuse; the file's vocabulary,
//    merges, added tokens, post-processor, truncation and padding stay. Its padding side defaults
//    to "left" (the class attribute) when the config names none.
//  - "PreTrainedTokenizerFast" / "TokenizersBackend" or no tokenizer_config.json: the file as is.
//  - any other class: ErrorCode::unsupported (transformers would rebuild it in its own way).
// A directory with tokenizer.model and no tokenizer.json is converted as transformers'
// GemmaTokenizer does it (vocabulary = the pieces, merges from generate_merges, control and
// user-defined pieces as added tokens, the post-processor from add_bos_token / add_eos_token);
// for any other class it is ErrorCode::unsupported. A directory with neither, but vocab.json and
// merges.txt (the files Qwen2Tokenizer saves, as in GR00T N1.6's Eagle directory), is read for
// Qwen2Tokenizer only, with its added tokens from added_tokens_decoder and the post-processor from
// add_bos_token / add_eos_token.
// Named special tokens of the config (bos/eos/unk/sep/pad/cls/mask, GemmaTokenizer's defaults when
// absent) missing from the added tokens are added as special tokens, as transformers does;
// add_bos_token / add_eos_token are ignored when tokenizer.json exists, as transformers drops them
// then. Only the tokenizer_class route is followed: the shortcut transformers takes for model
// types it maps to another class is not (SmolVLM's "smolvlm" and PaliGemma's "paligemma" types are
// not mapped, so this is their real route).
// Errors name the file: ErrorCode::not_found when no vocabulary file exists, format for a corrupt
// tokenizer.json / tokenizer.model / vocab.json / merges.txt / tokenizer_config.json, unsupported
// as above.
struct PretrainedTokenizer {
  Tokenizer tokenizer;
  std::string tokenizer_class;  // "" without tokenizer_config.json
  BatchOptions defaults;        // padding/truncation side and pad id from the config; max_length 0
  std::optional<int32_t> bos_token_id, eos_token_id, pad_token_id;
  std::string source;  // the file the vocabulary came from: <dir>/tokenizer.json, tokenizer.model or vocab.json
};
PretrainedTokenizer load_pretrained_tokenizer(const std::string& dir);

// A SentencePiece model file on its own, converted as load_pretrained_tokenizer converts a
// tokenizer.model for tokenizer_class GemmaTokenizer with no other tokenizer_config.json entry: the
// class's default special tokens, add_bos_token / add_eos_token false (so encode adds nothing),
// padding side left. For checkpoints whose tokenizer directory is not a transformers one (FluxVLA
// saves tokenizer.model next to a tokenizer_config.json naming its own "PaligemmaTokenizer"
// wrapper around libsentencepiece). Errors name the file (not_found when it does not exist).
PretrainedTokenizer load_gemma_sentencepiece(const std::string& model_path);

}  // namespace tether::text
