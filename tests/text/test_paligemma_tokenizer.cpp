// PaliGemma (GemmaTokenizer) parity for pi0 / pi0.5: ids, masks and decodes against transformers'
// AutoTokenizer on the stand-in repository (tools/oracle/paligemma_tokenizer_fixtures.py), through
// tokenizer.json and through tokenizer.model alone, plus the SentencePiece reader and load errors.
#include <gtest/gtest.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <sstream>

#include "core/error.h"
#include "core/json_util.h"
#include "text/pipeline.h"
#include "text/sentencepiece_model.h"
#include "text/tokenizer.h"
#include "scratch_dir.h"

namespace fs = std::filesystem;
using tether::Error;
using tether::ErrorCode;
using namespace tether::text;

namespace {

const fs::path kDir = fs::path(TETHER_FIXTURES_DIR) / "tokenizer" / "paligemma";

std::vector<Json> read_jsonl(const fs::path& path) {
  std::ifstream in(path);
  if (!in) throw std::runtime_error("cannot open " + path.string());
  std::vector<Json> rows;
  std::string line;
  while (std::getline(in, line))
    if (!line.empty()) rows.push_back(Json::parse(line));
  return rows;
}

std::string ids_str(const std::vector<int32_t>& ids) {
  std::ostringstream os;
  os << '[';
  for (std::size_t k = 0; k < ids.size(); ++k) os << (k ? "," : "") << ids[k];
  os << ']';
  return os.str();
}

// A fresh directory under the temp folder, removed with the object.
struct TempDir {
  fs::path path;
  explicit TempDir(const std::string& name)
      : path(tether::testing::scratch_dir() / ("pg_" + name)) {
    fs::remove_all(path);
    fs::create_directories(path);
  }
  ~TempDir() { fs::remove_all(path); }
  void copy(const std::string& file) const {
    fs::copy_file(kDir / file, path / file, fs::copy_options::overwrite_existing);
  }
  void write(const std::string& file, const std::string& content) const {
    std::ofstream(path / file, std::ios::binary) << content;
  }
};

// The fixture directory without tokenizer.json: transformers converts tokenizer.model.
struct ModelOnlyDir : TempDir {
  ModelOnlyDir() : TempDir("model_only") {
    for (const char* f : {"tokenizer.model", "tokenizer_config.json", "config.json"}) copy(f);
  }
};

const Json& meta() {
  static const Json m = read_jsonl(kDir / "expected.jsonl").front().at("meta");
  return m;
}

// Every corpus string through one route: ids with and without special tokens, decodes.
struct RouteResult {
  int strings = 0, failed = 0;
};
RouteResult check_route(const PretrainedTokenizer& p, const std::string& prefix) {
  RouteResult r;
  int printed = 0;
  auto fail = [&](const std::string& what) {
    ++r.failed;
    if (printed++ < 8) ADD_FAILURE() << prefix << ": " << what;
  };
  for (const Json& row : read_jsonl(kDir / "expected.jsonl")) {
    if (row.contains("meta")) continue;
    ++r.strings;
    const auto text = row["text"].get<std::string>();
    const std::string at =
        "string " + std::to_string(row["i"].get<int>()) + " " + Json(text).dump();
    const auto ids = row[prefix + "ids"].get<std::vector<int32_t>>();
    const auto plain = row[prefix + "ids_plain"].get<std::vector<int32_t>>();
    const auto got = p.tokenizer.encode(text), got_plain = p.tokenizer.encode(text, false);
    if (got != ids) fail(at + "\n  expected " + ids_str(ids) + "\n  got      " + ids_str(got));
    if (got_plain != plain)
      fail(at + " without special tokens\n  expected " + ids_str(plain) + "\n  got      " +
           ids_str(got_plain));
    if (prefix.empty()) {
      const std::string d = p.tokenizer.decode(ids, false);
      if (d != row["decode"].get<std::string>())
        fail("decode of " + at + ": got " + Json(d).dump());
    }
    const std::string ds = p.tokenizer.decode(ids, true);
    if (ds != row[prefix + "decode_skip"].get<std::string>())
      fail("decode(skip_special_tokens) of " + at + ": got " + Json(ds).dump());
  }
  return r;
}

TEST(PaliGemmaTokenizer, TokenizerJsonMatchesAutoTokenizer) {
  const PretrainedTokenizer p = load_pretrained_tokenizer(kDir.string());
  EXPECT_EQ(p.tokenizer_class, "GemmaTokenizer");
  EXPECT_EQ(p.source, (kDir / "tokenizer.json").string());
  EXPECT_EQ(p.tokenizer.vocab_size(), meta()["vocab_size"].get<int32_t>());
  EXPECT_EQ(p.defaults.pad_right, meta()["padding_side"] == "right");
  EXPECT_EQ(p.defaults.truncate_right, meta()["truncation_side"] == "right");
  EXPECT_EQ(p.pad_token_id, meta()["pad_token_id"].get<int32_t>());
  EXPECT_EQ(p.bos_token_id, meta()["bos_token_id"].get<int32_t>());
  EXPECT_EQ(p.eos_token_id, meta()["eos_token_id"].get<int32_t>());
  EXPECT_EQ(p.defaults.pad_token_id, meta()["pad_token_id"].get<int32_t>());
  EXPECT_EQ(p.tokenizer.num_special_tokens_to_add(), 1);
  const RouteResult r = check_route(p, "");
  std::printf("[parity] paligemma tokenizer.json: %d strings, %d mismatches\n", r.strings,
              r.failed);
  EXPECT_GE(r.strings, 200);
  EXPECT_EQ(r.strings, meta()["strings"].get<int>());
  EXPECT_EQ(r.failed, 0);
}

TEST(PaliGemmaTokenizer, TokenizerModelAloneMatchesAutoTokenizer) {
  const ModelOnlyDir dir;
  const PretrainedTokenizer p = load_pretrained_tokenizer(dir.path.string());
  EXPECT_EQ(p.tokenizer_class, "GemmaTokenizer");
  EXPECT_EQ(p.source, (dir.path / "tokenizer.model").string());
  EXPECT_EQ(p.tokenizer.vocab_size(), meta()["model_vocab_size"].get<int32_t>());
  EXPECT_EQ(p.defaults.pad_right, meta()["model_padding_side"] == "right");
  EXPECT_EQ(p.pad_token_id, meta()["pad_token_id"].get<int32_t>());
  EXPECT_EQ(p.bos_token_id, meta()["bos_token_id"].get<int32_t>());
  const RouteResult r = check_route(p, "model_");
  std::printf("[parity] paligemma tokenizer.model: %d strings, %d mismatches\n", r.strings,
              r.failed);
  EXPECT_GE(r.strings, 200);
  EXPECT_EQ(r.failed, 0);
}

// lerobot's TokenizerProcessorStep: padding "max_length", max_length 48 (pi0) / 200 (pi0.5),
// truncation, padding_side "right"; and other settings.
TEST(PaliGemmaTokenizer, BatchesMatchLerobotCalls) {
  const PretrainedTokenizer json_route = load_pretrained_tokenizer(kDir.string());
  const ModelOnlyDir dir;
  const PretrainedTokenizer model_route = load_pretrained_tokenizer(dir.path.string());
  int checked = 0;
  for (const Json& row : read_jsonl(kDir / "batch.jsonl")) {
    if (row.contains("meta")) continue;
    const PretrainedTokenizer& p = row["route"] == "json" ? json_route : model_route;
    BatchOptions opt = p.defaults;
    opt.padding = row["padding"] == "longest" ? Padding::longest : Padding::max_length;
    opt.max_length = row["max_length"].get<int>();
    opt.truncation = row["truncation"].get<bool>();
    if (!row["padding_side"].is_null()) opt.pad_right = row["padding_side"] == "right";
    const auto texts = row["texts"].get<std::vector<std::string>>();
    const BatchEncoding enc =
        encode_batch(p.tokenizer, texts, opt, row["add_special_tokens"].get<bool>());
    const auto ids = row["input_ids"].get<std::vector<std::vector<int64_t>>>();
    const auto mask = row["attention_mask"].get<std::vector<std::vector<int>>>();
    const std::string what = std::string(row["route"]) + " batch " + std::to_string(checked) +
                             " (" + std::string(row["padding"]) + ", max_length " +
                             std::to_string(opt.max_length) + ")";
    ASSERT_EQ(enc.batch, static_cast<int64_t>(ids.size())) << what;
    ASSERT_EQ(enc.length, static_cast<int64_t>(ids[0].size())) << what;
    for (std::size_t b = 0; b < ids.size(); ++b)
      for (std::size_t k = 0; k < ids[b].size(); ++k) {
        EXPECT_EQ(enc.ids[b * enc.length + k], ids[b][k]) << what << " row " << b << " pos " << k;
        EXPECT_EQ(enc.mask[b * enc.length + k], mask[b][k]) << what << " row " << b << " pos " << k;
      }
    ++checked;
  }
  std::printf("[parity] paligemma: %d transformers batches checked\n", checked);
  EXPECT_GE(checked, 40);
}

// Other tokenizer_config.json contents: add_bos_token / add_eos_token count for tokenizer.model
// alone and are dropped with tokenizer.json; sides, default tokens and special flags. One variant's
// tokenizer.json has other stages and BPE options, which the class replaces with its own.
TEST(PaliGemmaTokenizer, ConfigVariantsMatchAutoTokenizer) {
  int checked = 0;
  for (const Json& row : read_jsonl(kDir / "variants.jsonl")) {
    if (row.contains("meta")) continue;
    const auto name = row["name"].get<std::string>();
    const TempDir dir(name);
    for (const Json& f : row["files"]) dir.copy(f.get<std::string>());
    if (row.contains("tokenizer_json")) dir.write("tokenizer.json", row["tokenizer_json"].dump());
    dir.write("tokenizer_config.json", row["tokenizer_config"].dump());
    const PretrainedTokenizer p = load_pretrained_tokenizer(dir.path.string());
    EXPECT_EQ(p.defaults.pad_right, row["padding_side"] == "right") << name;
    EXPECT_EQ(p.defaults.truncate_right, row["truncation_side"] == "right") << name;
    EXPECT_EQ(p.pad_token_id, row["pad_token_id"].get<int32_t>()) << name;
    EXPECT_EQ(p.bos_token_id, row["bos_token_id"].get<int32_t>()) << name;
    EXPECT_EQ(p.eos_token_id, row["eos_token_id"].get<int32_t>()) << name;
    EXPECT_EQ(p.tokenizer.num_special_tokens_to_add(), row["num_special_tokens_to_add"].get<int>())
        << name;
    const auto texts = row["texts"].get<std::vector<std::string>>();
    for (std::size_t k = 0; k < texts.size(); ++k) {
      const auto expected = row["ids"][k].get<std::vector<int32_t>>();
      EXPECT_EQ(ids_str(p.tokenizer.encode(texts[k])), ids_str(expected))
          << name << " " << Json(texts[k]).dump();
      EXPECT_EQ(p.tokenizer.decode(expected, true), row["decode_skip"][k].get<std::string>())
          << name << " " << Json(texts[k]).dump();
    }
    ++checked;
  }
  EXPECT_GE(checked, 8);
}

// The decoders of the `tokenizers` package on token lists no encoding produces.
TEST(PaliGemmaTokenizer, DecodersMatchTokenizers) {
  int checked = 0;
  for (const Json& row : read_jsonl(kDir / "decoders.jsonl")) {
    if (row.contains("meta")) continue;
    const auto decoder = make_decoder(row["decoder"], "decoders.jsonl");
    EXPECT_EQ(decoder->decode(row["tokens"].get<std::vector<std::string>>()),
              row["text"].get<std::string>())
        << row["decoder"].dump() << " on " << row["tokens"].dump();
    ++checked;
  }
  EXPECT_GE(checked, 10);
}

// ---- SentencePiece model reader -----------------------------------------------------------------

std::string varint(uint64_t v) {
  std::string out;
  while (v >= 0x80) {
    out.push_back(static_cast<char>((v & 0x7F) | 0x80));
    v >>= 7;
  }
  out.push_back(static_cast<char>(v));
  return out;
}
std::string field_bytes(int field, const std::string& payload) {
  return varint(uint64_t(field) << 3 | 2) + varint(payload.size()) + payload;
}
std::string piece(const std::string& text, int type = 1) {
  return field_bytes(1, field_bytes(1, text) + varint(3 << 3) + varint(type));
}

TEST(SentencePieceModel, ReadsPiecesAndSkipsOtherFields) {
  // A trainer_spec (field 2) and a score (fixed32) are skipped or kept as they come.
  const std::string score = std::string("\x15\x00\x00\x80\xbf", 5);  // field 2, fixed32, -1.0f
  const std::string bytes = piece("<pad>", 3) + field_bytes(1, field_bytes(1, "a") + score) +
                            field_bytes(2, varint(3 << 3) + varint(2)) + piece("<x>", 4);
  const SentencePieceModel m = parse_sentencepiece_model(bytes, "t.model");
  ASSERT_EQ(m.pieces.size(), 3u);
  EXPECT_EQ(m.pieces[0].piece, "<pad>");
  EXPECT_EQ(m.pieces[0].type, SentencePiece::control);
  EXPECT_EQ(m.pieces[1].piece, "a");
  EXPECT_EQ(m.pieces[1].score, -1.0f);
  EXPECT_EQ(m.pieces[1].type, SentencePiece::normal);
  EXPECT_EQ(m.pieces[2].type, SentencePiece::user_defined);
  // The real model's pieces, in order.
  const SentencePieceModel real = read_sentencepiece_model((kDir / "tokenizer.model").string());
  EXPECT_EQ(real.pieces.size(), 640u);
  EXPECT_EQ(real.pieces[2].piece, "<bos>");
  EXPECT_EQ(real.pieces[7].piece, "<0x00>");
  EXPECT_EQ(real.pieces[7].type, SentencePiece::byte);
}

TEST(SentencePieceModel, MalformedDataIsAFormatErrorNamingTheFile) {
  const std::vector<std::pair<std::string, std::string>> cases = {
      {"", "no pieces"},
      {"{\"version\": \"1.0\"}", "not a SentencePiece model"},
      {piece("abc").substr(0, 5), "runs past the end"},
      {std::string("\x0a\xff", 2), "truncated varint"},
      {std::string("\x13", 1), "wire type 3"},
      {piece("a") + piece("a"), "appears twice"},
      {piece(""), "is empty"},
      {piece("\xc3\x28"), "not valid UTF-8"},
      {piece("a", 9), "unknown type"},
  };
  for (const auto& [bytes, fragment] : cases) {
    try {
      parse_sentencepiece_model(bytes, "dir/tokenizer.model");
      ADD_FAILURE() << "no error for '" << fragment << "'";
    } catch (const Error& e) {
      EXPECT_EQ(e.code(), ErrorCode::format) << e.what();
      const std::string msg = e.what();
      EXPECT_NE(msg.find("dir/tokenizer.model"), std::string::npos) << msg;
      EXPECT_NE(msg.find(fragment), std::string::npos) << "'" << fragment << "' not in: " << msg;
      EXPECT_EQ(msg.find('\n'), std::string::npos) << msg;
    }
  }
}

TEST(SentencePieceModel, GenerateMergesFollowsTransformers) {
  std::vector<SentencePiece> pieces;
  for (const char* p : {"a", "b", "ab", "abc", "c", "bc", "\xc3\xa9", "a\xc3\xa9"})
    pieces.push_back(SentencePiece{p});
  using M = std::vector<std::pair<std::string, std::string>>;
  EXPECT_EQ(generate_merges(pieces),
            (M{{"a", "b"}, {"a", "bc"}, {"ab", "c"}, {"b", "c"}, {"a", "\xc3\xa9"}}));
}

// The fixture's tokenizer.json was written by transformers from its tokenizer.model: the same
// vocabulary and merges, in the same order.
TEST(SentencePieceModel, ConversionEqualsTransformersTokenizerJson) {
  const SentencePieceModel m = read_sentencepiece_model((kDir / "tokenizer.model").string());
  const Json file = tether::read_json_file<Json>((kDir / "tokenizer.json").string());
  const Json& merges = file["model"]["merges"];
  const auto got = generate_merges(m.pieces);
  ASSERT_EQ(got.size(), merges.size());
  for (std::size_t k = 0; k < got.size(); ++k) {
    EXPECT_EQ(got[k].first, merges[k][0].get<std::string>()) << "merge " << k;
    EXPECT_EQ(got[k].second, merges[k][1].get<std::string>()) << "merge " << k;
  }
  const Json& vocab = file["model"]["vocab"];
  ASSERT_EQ(vocab.size(), m.pieces.size());
  for (std::size_t k = 0; k < m.pieces.size(); ++k)
    EXPECT_EQ(vocab.at(m.pieces[k].piece).get<std::size_t>(), k) << m.pieces[k].piece;
}

// ---- load and encode errors ---------------------------------------------------------------------

void expect_error(const fs::path& dir, ErrorCode code, const std::vector<std::string>& fragments) {
  try {
    load_pretrained_tokenizer(dir.string());
    ADD_FAILURE() << "expected an error mentioning " << fragments[0];
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), code) << e.what();
    const std::string msg = e.what();
    EXPECT_EQ(msg.find('\n'), std::string::npos) << msg;
    for (const std::string& f : fragments)
      EXPECT_NE(msg.find(f), std::string::npos) << "'" << f << "' not in: " << msg;
  }
}

TEST(PaliGemmaTokenizerErrors, NoTokenizerFiles) {
  const TempDir dir("empty");
  dir.copy("tokenizer_config.json");
  dir.copy("config.json");
  expect_error(dir.path, ErrorCode::not_found,
               {(dir.path / "tokenizer.json").string(), "tokenizer.model"});
}

TEST(PaliGemmaTokenizerErrors, CorruptFiles) {
  const TempDir dir("corrupt");
  dir.copy("tokenizer_config.json");
  dir.write("tokenizer.json", "{\"version\": \"1.0\", \"model\": {");
  expect_error(dir.path, ErrorCode::format, {(dir.path / "tokenizer.json").string()});

  fs::remove(dir.path / "tokenizer.json");
  std::ifstream in(kDir / "tokenizer.model", std::ios::binary);
  const std::string model((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  dir.write("tokenizer.model", model.substr(0, model.size() - 3));  // truncated
  expect_error(dir.path, ErrorCode::format, {(dir.path / "tokenizer.model").string()});
  dir.write("tokenizer.model", "not a model at all\n");
  expect_error(dir.path, ErrorCode::format,
               {(dir.path / "tokenizer.model").string(), "not a SentencePiece model"});

  fs::remove(dir.path / "tokenizer.model");
  fs::create_directory(dir.path / "tokenizer.model");  // exists, cannot be read as a file
  expect_error(dir.path, ErrorCode::io, {(dir.path / "tokenizer.model").string()});

  fs::remove(dir.path / "tokenizer.model");
  dir.write("tokenizer.model", model);
  dir.write("tokenizer_config.json", "{\"tokenizer_class\": ");
  expect_error(dir.path, ErrorCode::format, {(dir.path / "tokenizer_config.json").string()});
}

TEST(PaliGemmaTokenizerErrors, ModelWithoutGemmaClassIsUnsupported) {
  const TempDir dir("other_class");
  dir.copy("tokenizer.model");
  dir.write("tokenizer_config.json", R"({"tokenizer_class": "LlamaTokenizer"})");
  expect_error(dir.path, ErrorCode::unsupported, {"LlamaTokenizer"});
  dir.write("tokenizer_config.json", R"({"tokenizer_class": "PreTrainedTokenizerFast"})");
  expect_error(dir.path, ErrorCode::unsupported,
               {(dir.path / "tokenizer.model").string(), "PreTrainedTokenizerFast"});
  fs::remove(dir.path / "tokenizer_config.json");
  expect_error(dir.path, ErrorCode::unsupported,
               {(dir.path / "tokenizer.model").string(), "no tokenizer_class"});
}

TEST(PaliGemmaTokenizerErrors, InvalidUtf8TextNamesTheTokenizer) {
  const PretrainedTokenizer p = load_pretrained_tokenizer(kDir.string());
  for (const std::string& bad :
       {std::string("pick \xff up"), std::string("\xc3\x28"), std::string("ok \xe6\x97")}) {
    try {
      p.tokenizer.encode(bad);
      ADD_FAILURE() << "no error";
    } catch (const Error& e) {
      EXPECT_EQ(e.code(), ErrorCode::invalid_argument);
      const std::string msg = e.what();
      EXPECT_NE(msg.find("UTF-8"), std::string::npos) << msg;
      EXPECT_NE(msg.find((kDir / "tokenizer.json").string()), std::string::npos) << msg;
    }
    BatchOptions opt = p.defaults;
    opt.padding = Padding::max_length;
    opt.max_length = 48;
    EXPECT_THROW(encode_batch(p.tokenizer, {"fine", bad}, opt), Error);
  }
}

}  // namespace
