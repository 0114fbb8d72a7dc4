// The configurable stages of a tokenizer.json around the model: normalizers, pre-tokenizers,
// post-processors and the decoder, each built from its JSON object (unknown types are rejected
// with ErrorCode::unsupported naming the field).
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "core/json_util.h"
#include "text/added_vocabulary.h"

namespace tether::text {

using Json = JsonMap;  // see bpe.h

class Normalizer {
 public:
  virtual ~Normalizer() = default;
  virtual std::string normalize(std::string_view s) const = 0;
};
// Null JSON gives nullptr (no normalisation). `where` is e.g. "path: normalizer".
std::unique_ptr<Normalizer> make_normalizer(const Json& j, const std::string& where);

class PreTokenizer {
 public:
  virtual ~PreTokenizer() = default;
  // Splits (and may rewrite) the pieces that are not resolved added tokens.
  virtual void pre_tokenize(std::vector<Piece>& pieces) const = 0;
};
std::unique_ptr<PreTokenizer> make_pre_tokenizer(const Json& j, const std::string& where);

class PostProcessor {
 public:
  virtual ~PostProcessor() = default;
  virtual int added_tokens_single() const = 0;
  virtual void process(std::vector<int32_t>& ids, bool add_special_tokens) const = 0;
};
std::unique_ptr<PostProcessor> make_post_processor(const Json& j, const std::string& where);

class Decoder {
 public:
  virtual ~Decoder() = default;
  // The crate's decode_chain: each decoder maps the token strings to new ones (a Sequence feeds
  // them from one decoder to the next); the decoded text is their concatenation.
  virtual std::vector<std::string> decode_chain(std::vector<std::string> tokens) const = 0;
  std::string decode(std::vector<std::string> tokens) const;
};
std::unique_ptr<Decoder> make_decoder(const Json& j, const std::string& where);

// GPT-2's byte <-> printable-character table used by the ByteLevel stages.
const std::string& byte_to_unicode(unsigned char b);  // UTF-8 of the character standing for `b`
int byte_from_unicode(char32_t c);                    // -1 when `c` stands for no byte

}  // namespace tether::text
