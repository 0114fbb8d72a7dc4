// SentencePiece ModelProto reader (protobuf wire format, no protobuf library) and transformers'
// generate_merges, which turns the pieces of a SentencePiece model into ranked BPE merges.
#include "text/sentencepiece_model.h"

#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <unordered_set>

#include "core/error.h"
#include "text/unicode.h"

namespace tether::text {

namespace {

// A cursor over protobuf wire data; every read checks the bounds and throws a format error naming
// the file and the byte offset.
class Wire {
 public:
  Wire(std::string_view data, const std::string& where, std::size_t base = 0)
      : data_(data), where_(where), base_(base) {}
  bool done() const { return pos_ >= data_.size(); }
  std::size_t offset() const { return base_ + pos_; }

  uint64_t varint() {
    uint64_t v = 0;
    for (int shift = 0; shift < 64; shift += 7) {
      if (done()) fail("truncated varint");
      const auto b = static_cast<unsigned char>(data_[pos_++]);
      v |= uint64_t(b & 0x7F) << shift;
      if (!(b & 0x80)) return v;
    }
    fail("varint longer than 10 bytes");
  }
  // Reads a field key; `field` and `wire_type` receive its parts.
  void key(uint32_t& field, int& wire_type) {
    const std::size_t at = offset();
    const uint64_t k = varint();
    field = static_cast<uint32_t>(k >> 3);
    wire_type = static_cast<int>(k & 7);
    if (field == 0 || k >> 32) fail_at(at, "invalid field number");
  }
  std::string_view bytes() {
    const uint64_t n = varint();
    if (n > data_.size() - pos_) fail("length-delimited field runs past the end of the data");
    std::string_view out = data_.substr(pos_, static_cast<std::size_t>(n));
    pos_ += static_cast<std::size_t>(n);
    return out;
  }
  uint32_t fixed32() {
    if (data_.size() - pos_ < 4) fail("truncated fixed32 field");
    uint32_t v = 0;
    for (int k = 3; k >= 0; --k) v = (v << 8) | static_cast<unsigned char>(data_[pos_ + k]);
    pos_ += 4;
    return v;
  }
  void skip(int wire_type) {
    switch (wire_type) {
      case 0:
        varint();
        return;
      case 1:
        if (data_.size() - pos_ < 8) fail("truncated fixed64 field");
        pos_ += 8;
        return;
      case 2:
        bytes();
        return;
      case 5:
        fixed32();
        return;
      default:
        fail("unsupported wire type " + std::to_string(wire_type));
    }
  }
  [[noreturn]] void fail(const std::string& what) const { fail_at(offset(), what); }
  [[noreturn]] void fail_at(std::size_t at, const std::string& what) const {
    throw Error(ErrorCode::format, where_ + ": not a SentencePiece model (" + what + " at byte " +
                                       std::to_string(at) + ")");
  }

 private:
  std::string_view data_;
  const std::string& where_;
  std::size_t base_, pos_ = 0;
};

SentencePiece parse_piece(Wire& outer, std::string_view data, const std::string& where,
                          std::size_t index) {
  Wire w(data, where, outer.offset() - data.size());
  SentencePiece p;
  bool has_piece = false;
  while (!w.done()) {
    uint32_t field;
    int wt;
    w.key(field, wt);
    if (field == 1 && wt == 2) {
      p.piece = std::string(w.bytes());
      has_piece = true;
    } else if (field == 2 && wt == 5) {
      const uint32_t bits = w.fixed32();
      std::memcpy(&p.score, &bits, sizeof(float));
    } else if (field == 3 && wt == 0) {
      const uint64_t t = w.varint();
      if (t < 1 || t > 6)
        throw Error(ErrorCode::format, where + ": piece " + std::to_string(index) +
                                           " has the unknown type " + std::to_string(t));
      p.type = static_cast<SentencePiece::Type>(t);
    } else {
      w.skip(wt);
    }
  }
  const std::string id = "piece " + std::to_string(index);
  if (!has_piece || p.piece.empty())
    throw Error(ErrorCode::format, where + ": " + id + " is empty");
  if (find_invalid_utf8(p.piece) != std::string::npos)
    throw Error(ErrorCode::format, where + ": " + id + " is not valid UTF-8");
  return p;
}

}  // namespace

SentencePieceModel parse_sentencepiece_model(std::string_view bytes, const std::string& where) {
  SentencePieceModel m;
  Wire w(bytes, where);
  while (!w.done()) {
    uint32_t field;
    int wt;
    w.key(field, wt);
    if (field == 1) {
      if (wt != 2) w.fail("ModelProto.pieces is not a message");
      const std::string_view piece = w.bytes();
      m.pieces.push_back(parse_piece(w, piece, where, m.pieces.size()));
    } else {
      w.skip(wt);
    }
  }
  if (m.pieces.empty())
    throw Error(ErrorCode::format, where + ": not a SentencePiece model (no pieces)");
  std::unordered_set<std::string_view> seen;
  for (std::size_t k = 0; k < m.pieces.size(); ++k)
    if (!seen.insert(m.pieces[k].piece).second)
      throw Error(ErrorCode::format, where + ": piece " + std::to_string(k) + " '" +
                                         m.pieces[k].piece + "' appears twice");
  return m;
}

SentencePieceModel read_sentencepiece_model(const std::string& path) {
  std::error_code ec;
  if (!std::filesystem::exists(path, ec))
    throw Error(ErrorCode::not_found, path + ": no such file");
  if (!std::filesystem::is_regular_file(path, ec))
    throw Error(ErrorCode::io, path + ": cannot read (not a regular file)");
  std::ifstream in(path, std::ios::binary);
  if (!in) throw Error(ErrorCode::io, path + ": cannot open");
  std::ostringstream ss;
  ss << in.rdbuf();
  if (in.bad()) throw Error(ErrorCode::io, path + ": read failed");
  return parse_sentencepiece_model(ss.str(), path);
}

std::vector<std::pair<std::string, std::string>> generate_merges(
    const std::vector<SentencePiece>& pieces) {
  std::unordered_set<std::string_view> vocab;
  vocab.reserve(pieces.size());
  for (const SentencePiece& p : pieces) vocab.insert(p.piece);
  std::vector<std::pair<std::string, std::string>> merges;
  for (const SentencePiece& p : pieces) {
    const std::string_view s = p.piece;
    for (std::size_t cut = utf8_len(static_cast<unsigned char>(s[0])); cut < s.size();
         cut += utf8_len(static_cast<unsigned char>(s[cut]))) {
      const std::string_view left = s.substr(0, cut), right = s.substr(cut);
      if (vocab.count(left) && vocab.count(right)) merges.emplace_back(left, right);
    }
  }
  return merges;
}

}  // namespace tether::text
