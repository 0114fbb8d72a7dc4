// Reader for SentencePiece model files (tokenizer.model, a serialized ModelProto): the pieces with
// their scores and types, and the vocabulary/merges transformers derives from them for a BPE class.
#pragma once

#include <string>
#include <string_view>
#include <utility>
#include <vector>

namespace tether::text {

struct SentencePiece {
  // ModelProto.SentencePiece.Type
  enum Type { normal = 1, unknown = 2, control = 3, user_defined = 4, unused = 5, byte = 6 };
  std::string piece;
  float score = 0.0f;
  Type type = normal;
};

struct SentencePieceModel {
  std::vector<SentencePiece> pieces;  // in id order
};

// Parses the protobuf wire format; only ModelProto.pieces is kept, every other field is skipped.
// Errors (ErrorCode::format) name `where`: malformed wire data, a truncated file, a piece that is
// empty, not valid UTF-8 or repeated, an unknown piece type, or no pieces at all.
SentencePieceModel parse_sentencepiece_model(std::string_view bytes, const std::string& where);
// Reads and parses `path`: ErrorCode::not_found when it does not exist, io when it cannot be read.
SentencePieceModel read_sentencepiece_model(const std::string& path);

// transformers' generate_merges(vocab) (tokenization_utils_base.py) for the vocabulary {piece: id}:
// every split of a piece into two pieces of the vocabulary, ordered by the id of the merged piece,
// then by the length in characters of the left part.
std::vector<std::pair<std::string, std::string>> generate_merges(
    const std::vector<SentencePiece>& pieces);

}  // namespace tether::text
