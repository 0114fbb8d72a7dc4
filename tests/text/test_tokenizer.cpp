// Tokenizer parity against ids produced by the Python `tokenizers` / `transformers` packages
// (fixtures from tools/oracle/tokenizer_fixtures.py), plus decode, batching and error handling.
#include <gtest/gtest.h>

#include <chrono>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <sstream>
#include <thread>

#include "core/error.h"
#include "core/json_util.h"
#include "core/safetensors.h"
#include "text/onig_regex.h"
#include "text/tokenizer.h"
#include "text/unicode.h"
#include "scratch_dir.h"

namespace fs = std::filesystem;
using tether::Error;
using tether::ErrorCode;
using tether::Json;
using namespace tether::text;

namespace {

const fs::path kDir = fs::path(TETHER_FIXTURES_DIR) / "tokenizer";

std::vector<Json> read_jsonl(const fs::path& path) {
  std::ifstream in(path);
  if (!in) throw std::runtime_error("cannot open " + path.string());
  std::vector<Json> rows;
  std::string line;
  while (std::getline(in, line))
    if (!line.empty()) rows.push_back(Json::parse(line));
  return rows;
}

const std::vector<std::string>& cases() {
  static const std::vector<std::string> texts = [] {
    std::vector<std::string> out;
    for (const Json& row : read_jsonl(kDir / "cases.jsonl")) {
      if (row.contains("meta")) continue;
      const auto i = row["i"].get<std::size_t>();
      if (out.size() <= i) out.resize(i + 1);
      out[i] = row["text"].get<std::string>();
    }
    return out;
  }();
  return texts;
}

std::string escaped(const std::string& s) {
  std::string out;
  for (unsigned char c : s) {
    if (c == '\n') {
      out += "\\n";
    } else if (c == '\r') {
      out += "\\r";
    } else if (c == '\t') {
      out += "\\t";
    } else if (c < 0x20) {
      char buf[8];
      std::snprintf(buf, sizeof(buf), "\\x%02X", c);
      out += buf;
    } else {
      out += static_cast<char>(c);
    }
  }
  return out;
}

std::string ids_str(const std::vector<int32_t>& ids) {
  std::ostringstream os;
  os << '[';
  for (std::size_t k = 0; k < ids.size(); ++k) os << (k ? "," : "") << ids[k];
  os << ']';
  return os.str();
}

struct ParityResult {
  int checked = 0, failed = 0;
};

// A fixture directory with a tokenizer_config.json is loaded the transformers way.
Tokenizer load_fixture(const std::string& name) {
  if (fs::exists(kDir / name / "tokenizer_config.json"))
    return Tokenizer::from_transformers_dir((kDir / name).string());
  return Tokenizer::from_file((kDir / name / "tokenizer.json").string());
}

// Runs every expectation of one fixture tokenizer; prints the first few mismatches in full.
ParityResult run_parity(const std::string& name) {
  const Tokenizer tok = load_fixture(name);
  ParityResult r;
  int stride = 1;
  int printed = 0;
  auto fail = [&](const std::string& what) {
    ++r.failed;
    if (printed++ < 8) ADD_FAILURE() << name << ": " << what;
  };
  for (const Json& row : read_jsonl(kDir / name / "expected.jsonl")) {
    if (row.contains("meta")) {
      EXPECT_EQ(tok.vocab_size(), row["meta"]["vocab_size"].get<int32_t>()) << name;
      stride = row["meta"].value("special_stride", 1);
      continue;
    }
    const auto i = row["i"].get<std::size_t>();
    const std::string& text = cases().at(i);
    const auto expected = row["ids"].get<std::vector<int32_t>>();
    ++r.checked;
    const auto got = tok.encode(text, /*add_special_tokens=*/false);
    if (got != expected)
      fail("case " + std::to_string(i) + " '" + escaped(text) + "'\n  expected " +
           ids_str(expected) + "\n  got      " + ids_str(got));
    if (i % static_cast<std::size_t>(stride) == 0) {
      const auto expected_special =
          row.contains("ids_special") ? row["ids_special"].get<std::vector<int32_t>>() : expected;
      ++r.checked;
      const auto got_special = tok.encode(text, /*add_special_tokens=*/true);
      if (got_special != expected_special)
        fail("case " + std::to_string(i) + " with special tokens '" + escaped(text) +
             "'\n  expected " + ids_str(expected_special) + "\n  got      " + ids_str(got_special));
      if (row.contains("decode")) {
        r.checked += 2;
        const std::string d = tok.decode(expected_special, false),
                          ds = tok.decode(expected_special, true);
        if (d != row["decode"].get<std::string>())
          fail("decode of case " + std::to_string(i) + ": expected '" +
               escaped(row["decode"].get<std::string>()) + "' got '" + escaped(d) + "'");
        if (ds != row["decode_skip"].get<std::string>())
          fail("decode(skip_special) of case " + std::to_string(i) + ": expected '" +
               escaped(row["decode_skip"].get<std::string>()) + "' got '" + escaped(ds) + "'");
      }
    }
  }
  std::printf("[parity] %-10s %5d checks, %d failed\n", name.c_str(), r.checked, r.failed);
  return r;
}

class FixtureParity : public ::testing::TestWithParam<std::string> {};

TEST_P(FixtureParity, MatchesPythonTokenizers) {
  const ParityResult r = run_parity(GetParam());
  EXPECT_GT(r.checked, 100);
  EXPECT_EQ(r.failed, 0);
}

INSTANTIATE_TEST_SUITE_P(Tokenizers, FixtureParity,
                         ::testing::Values("smollm", "gpt2", "llama3", "qwen2", "misc", "fallback",
                                           "gpt2_trunc", "smollm_gpt2cls", "gpt2_config_flags", "qwen2_vocab_merges"));

// Byte-level BPE without normalizer or stripping added tokens is lossless.
TEST(Tokenizer, RoundTripDecode) {
  for (const char* name : {"gpt2", "llama3", "qwen2"}) {
    const Tokenizer tok = Tokenizer::from_file((kDir / name / "tokenizer.json").string());
    const bool nfc = std::string(name) == "qwen2";
    int failed = 0;
    for (const std::string& text : cases()) {
      const std::string expected = nfc ? normalize(text, NormalForm::nfc) : text;
      const std::string back = tok.decode(tok.encode(text, false), /*skip_special_tokens=*/false);
      if (back != expected && failed++ < 5)
        ADD_FAILURE() << name << ": '" << escaped(text) << "' -> '" << escaped(back) << "'";
    }
    EXPECT_EQ(failed, 0) << name;
  }
}

TEST(Tokenizer, BatchMatchesTransformers) {
  std::map<std::string, Tokenizer> toks;
  int checked = 0;
  for (const Json& row : read_jsonl(kDir / "batch.jsonl")) {
    if (row.contains("meta")) continue;
    const auto name = row["tokenizer"].get<std::string>();
    if (!toks.count(name)) toks.emplace(name, load_fixture(name));
    BatchOptions opt;
    if (fs::exists(kDir / name / "tokenizer_config.json")) {
      // Sides and pad id come from the config, as transformers takes them.
      opt = load_pretrained_tokenizer((kDir / name).string()).defaults;
      EXPECT_EQ(opt.pad_right, row["padding_side"] == "right");
      EXPECT_EQ(opt.truncate_right, row["truncation_side"] == "right");
      EXPECT_EQ(opt.pad_token_id, row["pad_token_id"].get<int32_t>());
    } else {
      opt.pad_right = row["padding_side"] == "right";
      opt.truncate_right = row["truncation_side"] == "right";
      opt.pad_token_id = row["pad_token_id"].get<int32_t>();
    }
    opt.padding = row["padding"] == "longest" ? Padding::longest : Padding::max_length;
    opt.max_length = row["max_length"].get<int>();
    opt.truncation = true;
    const auto texts = row["texts"].get<std::vector<std::string>>();
    const BatchEncoding enc =
        encode_batch(toks.at(name), texts, opt, row["add_special_tokens"].get<bool>());
    const auto ids = row["input_ids"].get<std::vector<std::vector<int64_t>>>();
    const auto mask = row["attention_mask"].get<std::vector<std::vector<int>>>();
    ASSERT_EQ(enc.batch, static_cast<int64_t>(ids.size()));
    ASSERT_EQ(enc.length, static_cast<int64_t>(ids[0].size()))
        << name << " " << row["padding"] << " " << opt.max_length;
    for (std::size_t b = 0; b < ids.size(); ++b) {
      for (std::size_t k = 0; k < ids[b].size(); ++k) {
        EXPECT_EQ(enc.ids[b * enc.length + k], ids[b][k]) << name << " row " << b << " pos " << k;
        EXPECT_EQ(enc.mask[b * enc.length + k], mask[b][k]) << name << " row " << b << " pos " << k;
      }
    }
    ++checked;
  }
  std::printf("[parity] %d transformers batches checked\n", checked);
  EXPECT_GT(checked, 20);
}

TEST(Tokenizer, PretrainedDirFollowsTransformers) {
  const PretrainedTokenizer p = load_pretrained_tokenizer((kDir / "smollm_gpt2cls").string());
  EXPECT_EQ(p.tokenizer_class, "GPT2Tokenizer");
  EXPECT_FALSE(p.defaults.truncate_right);
  EXPECT_TRUE(p.defaults.pad_right);
  EXPECT_EQ(p.pad_token_id, p.tokenizer.token_to_id("<|im_end|>"));
  EXPECT_EQ(p.bos_token_id, p.tokenizer.token_to_id("<|im_start|>"));
  EXPECT_EQ(p.eos_token_id, p.tokenizer.token_to_id("<end_of_utterance>"));
  // The named mask token is missing from tokenizer.json and gets the next id, marked special.
  const auto mask = p.tokenizer.token_to_id("<mask_tok>");
  ASSERT_TRUE(mask.has_value());
  EXPECT_EQ(*mask, p.tokenizer.vocab_size() - 1);
  EXPECT_EQ(p.tokenizer.decode({*mask}, /*skip_special_tokens=*/true), "");
  // GPT2Tokenizer drops the file's Digits pre-tokenizer, so numbers tokenize differently.
  const Tokenizer raw = Tokenizer::from_file((kDir / "smollm_gpt2cls" / "tokenizer.json").string());
  EXPECT_NE(p.tokenizer.encode(" 2024 12345"), raw.encode(" 2024 12345"));

  const fs::path bad = tether::testing::scratch_dir() / "tok_cls";
  fs::create_directories(bad);
  fs::copy_file(kDir / "smollm" / "tokenizer.json", bad / "tokenizer.json",
                fs::copy_options::overwrite_existing);
  std::ofstream(bad / "tokenizer_config.json") << R"({"tokenizer_class": "LlamaTokenizer"})";
  try {
    load_pretrained_tokenizer(bad.string());
    FAIL();
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::unsupported);
    EXPECT_NE(std::string(e.what()).find("LlamaTokenizer"), std::string::npos);
  }
  fs::remove_all(bad);
}

// The lerobot SmolVLA oracle's language tokens (tests/fixtures/smolvla, made by the upstream
// pre-processor: task + "\n", padding longest, max_length 48, the checkpoint's truncation side).
TEST(Tokenizer, MatchesSmolVlaOracleLanguageTokens) {
  const fs::path root = fs::path(TETHER_FIXTURES_DIR) / "smolvla";
  if (!fs::exists(root)) GTEST_SKIP() << "no SmolVLA oracle fixtures";
  int checked = 0;
  for (const auto& entry : fs::directory_iterator(root)) {
    const fs::path oracle = entry.path() / "oracle.safetensors";
    if (!fs::exists(oracle)) continue;
    const auto file = tether::SafeTensorsFile::open(oracle.string());
    const auto instructions =
        Json::parse(file.metadata().at("instructions")).get<std::vector<std::string>>();
    const tether::Tensor tokens = file.get("pre.lang_tokens"), mask = file.get("pre.lang_mask");
    ASSERT_EQ(tokens.dtype, tether::DType::i64);
    const PretrainedTokenizer p =
        load_pretrained_tokenizer((entry.path() / "checkpoint" / "vlm").string());
    BatchOptions opt = p.defaults;
    opt.padding = Padding::longest;
    opt.max_length = 48;
    std::vector<std::string> texts;
    for (const std::string& t : instructions)
      texts.push_back(!t.empty() && t.back() == '\n' ? t : t + "\n");
    const BatchEncoding enc = encode_batch(p.tokenizer, texts, opt);
    ASSERT_EQ(enc.batch, tokens.dim(0)) << oracle;
    ASSERT_EQ(enc.length, tokens.dim(1)) << oracle;
    // The mapped file gives no alignment guarantee for i64 data: copy it out.
    std::vector<int64_t> expected_ids(static_cast<std::size_t>(tokens.numel()));
    std::memcpy(expected_ids.data(), tokens.data, tokens.nbytes());
    for (int64_t k = 0; k < tokens.numel(); ++k) {
      EXPECT_EQ(enc.ids[k], expected_ids[k]) << oracle << " position " << k;
      EXPECT_EQ(enc.mask[k], mask.as<uint8_t>()[k]) << oracle << " position " << k;
    }
    ++checked;
  }
  std::printf("[parity] %d SmolVLA oracle cases' language tokens checked\n", checked);
  EXPECT_GT(checked, 0);
}

TEST(Tokenizer, BatchRaggedIsAnError) {
  const Tokenizer tok = Tokenizer::from_file((kDir / "gpt2" / "tokenizer.json").string());
  BatchOptions opt;
  opt.padding = Padding::none;
  EXPECT_THROW(encode_batch(tok, {"a", "a much longer sentence"}, opt), Error);
  opt.padding = Padding::max_length;
  opt.max_length = 2;
  opt.truncation = false;
  EXPECT_THROW(encode_batch(tok, {"a", "a much longer sentence"}, opt), Error);
  opt.truncation = true;
  const BatchEncoding enc = encode_batch(tok, {"a", "a much longer sentence"}, opt);
  EXPECT_EQ(enc.length, 2);
}

TEST(Tokenizer, AddedTokensAndVocabulary) {
  const Tokenizer tok = Tokenizer::from_file((kDir / "smollm" / "tokenizer.json").string());
  const auto im_start = tok.token_to_id("<|im_start|>");
  ASSERT_TRUE(im_start.has_value());
  EXPECT_EQ(tok.id_to_token(*im_start), "<|im_start|>");
  EXPECT_EQ(tok.encode("<|im_start|>", false), std::vector<int32_t>{*im_start});
  EXPECT_FALSE(tok.token_to_id("<|not a token|>").has_value());
  EXPECT_EQ(tok.num_special_tokens_to_add(), 0);
  // Unknown ids are skipped when decoding, as the crate does.
  EXPECT_EQ(tok.decode({*im_start, 1 << 30}), "<|im_start|>");
  EXPECT_EQ(tok.decode({*im_start}, /*skip_special_tokens=*/true), "");
  const Tokenizer llama = Tokenizer::from_file((kDir / "llama3" / "tokenizer.json").string());
  EXPECT_EQ(llama.num_special_tokens_to_add(), 1);
}

TEST(Tokenizer, InvalidUtf8InputIsRejected) {
  const Tokenizer tok = Tokenizer::from_file((kDir / "gpt2" / "tokenizer.json").string());
  try {
    tok.encode(std::string("ok \xC3\x28", 5));
    FAIL() << "expected an error";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::invalid_argument);
    EXPECT_NE(std::string(e.what()).find("UTF-8"), std::string::npos);
  }
}

// ---- load errors -------------------------------------------------------------------------------

Json base_json() { return tether::read_json_file((kDir / "gpt2" / "tokenizer.json").string()); }

void expect_load_error(const Json& j, ErrorCode code, const std::vector<std::string>& fragments) {
  const std::string where = "test/tokenizer.json";
  try {
    Tokenizer::from_json_string(j.dump(), where);
    FAIL() << "expected an error mentioning " << fragments[0];
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), code) << e.what();
    const std::string msg = e.what();
    EXPECT_NE(msg.find(where), std::string::npos) << msg;
    for (const std::string& f : fragments)
      EXPECT_NE(msg.find(f), std::string::npos) << "'" << f << "' not in: " << msg;
  }
}

TEST(TokenizerErrors, MissingFile) {
  try {
    Tokenizer::from_file("/nonexistent/dir/tokenizer.json");
    FAIL();
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::not_found);
    EXPECT_NE(std::string(e.what()).find("/nonexistent/dir/tokenizer.json"), std::string::npos);
  }
}

TEST(TokenizerErrors, MalformedJson) {
  const fs::path path = tether::testing::scratch_dir() / "bad_tokenizer.json";
  std::ofstream(path) << "{\"version\": \"1.0\", \"model\": {";
  try {
    Tokenizer::from_file(path.string());
    FAIL();
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::format);
    EXPECT_NE(std::string(e.what()).find(path.string()), std::string::npos);
  }
  fs::remove(path);
  EXPECT_THROW(Tokenizer::from_json_string("[1, 2", "inline"), Error);
}

TEST(TokenizerErrors, UnsupportedComponentsAreNamed) {
  Json j = base_json();
  j["normalizer"] = Json{{"type", "BertNormalizer"}};
  expect_load_error(j, ErrorCode::unsupported, {"normalizer", "BertNormalizer"});

  j = base_json();
  j["normalizer"] =
      Json{{"type", "Sequence"},
           {"normalizers", Json::array({Json{{"type", "NFC"}}, Json{{"type", "StripAccents"}}})}};
  expect_load_error(j, ErrorCode::unsupported, {"normalizer.normalizers[1]", "StripAccents"});

  j = base_json();
  j["pre_tokenizer"] = Json{{"type", "Metaspace"}, {"replacement", "_"}};
  expect_load_error(j, ErrorCode::unsupported, {"pre_tokenizer", "Metaspace"});

  j = base_json();
  j["post_processor"] = Json{{"type", "BertProcessing"}};
  expect_load_error(j, ErrorCode::unsupported, {"post_processor", "BertProcessing"});

  j = base_json();
  j["decoder"] = Json{{"type", "WordPiece"}};
  expect_load_error(j, ErrorCode::unsupported, {"decoder", "WordPiece"});

  j = base_json();
  j["model"]["type"] = "Unigram";
  expect_load_error(j, ErrorCode::unsupported, {"model.type", "Unigram"});

  j = base_json();
  j["model"]["dropout"] = 0.1;
  expect_load_error(j, ErrorCode::unsupported, {"dropout"});

  j = base_json();
  j["pre_tokenizer"] = Json{{"type", "Split"},
                            {"pattern", Json{{"Regex", "a"}}},
                            {"behavior", "Sideways"},
                            {"invert", false}};
  expect_load_error(j, ErrorCode::unsupported, {"behavior", "Sideways"});
}

// vocab.json + merges.txt without tokenizer.json: a bad merges line is named by file and line, and what Tether
// does not rebuild (another class, no added_tokens_decoder) is refused rather than tokenized differently.
TEST(TokenizerErrors, VocabAndMergesFilesAreChecked) {
  const fs::path good = kDir / "qwen2_vocab_merges";
  const fs::path dir = tether::testing::scratch_dir() / "qwen2_vocab_merges_errors";
  auto fresh_copy = [&] {
    fs::remove_all(dir);
    fs::create_directories(dir);
    for (const char* f : {"vocab.json", "merges.txt", "tokenizer_config.json"}) fs::copy_file(good / f, dir / f);
  };
  auto expect_error = [&](ErrorCode code, const std::string& file, const std::string& fragment) {
    try {
      load_pretrained_tokenizer(dir.string());
      ADD_FAILURE() << "expected an error mentioning " << fragment;
    } catch (const Error& e) {
      EXPECT_EQ(e.code(), code) << e.what();
      const std::string msg = e.what();
      EXPECT_NE(msg.find((dir / file).string()), std::string::npos) << msg;
      EXPECT_NE(msg.find(fragment), std::string::npos) << msg;
    }
  };
  fresh_copy();
  EXPECT_EQ(load_pretrained_tokenizer(dir.string()).source, (dir / "vocab.json").string());

  std::ofstream(dir / "merges.txt", std::ios::app) << "one_symbol\n";
  const auto lines = [&] {
    std::ifstream in(dir / "merges.txt");
    return std::count(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>(), '\n');
  }();
  expect_error(ErrorCode::format, "merges.txt", "line " + std::to_string(lines));

  fresh_copy();
  Json config = tether::read_json_file<Json>((dir / "tokenizer_config.json").string());
  config.erase("added_tokens_decoder");
  std::ofstream(dir / "tokenizer_config.json") << config.dump();
  expect_error(ErrorCode::unsupported, "tokenizer_config.json", "added_tokens_decoder");

  fresh_copy();
  config = tether::read_json_file<Json>((dir / "tokenizer_config.json").string());
  config["tokenizer_class"] = "GPT2Tokenizer";
  std::ofstream(dir / "tokenizer_config.json") << config.dump();
  expect_error(ErrorCode::unsupported, "vocab.json", "GPT2Tokenizer");

  fresh_copy();
  std::ofstream(dir / "vocab.json") << "[1, 2]";
  expect_error(ErrorCode::format, "vocab.json", "not an object");
  fs::remove_all(dir);
}

TEST(TokenizerErrors, MalformedFieldsAreNamed) {
  Json j = base_json();
  j.erase("model");
  expect_load_error(j, ErrorCode::not_found, {"model"});

  j = base_json();
  j["model"]["merges"] = Json::array({"Ġ zzz_not_in_vocab"});
  expect_load_error(j, ErrorCode::format, {"model.merges[0]", "zzz_not_in_vocab"});

  j = base_json();
  j["model"]["merges"] = Json::array({"a b c"});
  expect_load_error(j, ErrorCode::format, {"model.merges[0]"});

  j = base_json();
  j["pre_tokenizer"] = Json{{"type", "Split"},
                            {"pattern", Json{{"Regex", "(unclosed"}}},
                            {"behavior", "Isolated"},
                            {"invert", false}};
  expect_load_error(j, ErrorCode::format, {"pre_tokenizer.pattern", "(unclosed"});

  j = base_json();
  j["post_processor"] = Json{
      {"type", "TemplateProcessing"},
      {"single", Json::array({Json{{"SpecialToken", Json{{"id", "<missing>"}, {"type_id", 0}}}}})},
      {"special_tokens", Json::object()}};
  expect_load_error(j, ErrorCode::format, {"post_processor.single[0]", "<missing>"});

  j = base_json();
  j["added_tokens"][0].erase("content");
  expect_load_error(j, ErrorCode::not_found, {"added_tokens[0]", "content"});
}

// ---- regex dialect -----------------------------------------------------------------------------

std::vector<std::pair<std::size_t, std::size_t>> matches(const std::string& pattern,
                                                         const std::string& text) {
  return OnigRegex(pattern, "test").find_all(text);
}

using Spans = std::vector<std::pair<std::size_t, std::size_t>>;

// Expected spans below were observed with the Rust crate (Split / Replace over onig).
TEST(OnigRegex, EmptyMatchesFollowTheOnigCrate) {
  EXPECT_EQ(matches("x*", "xxaxx"), (Spans{{0, 2}, {3, 5}}));
  EXPECT_EQ(matches("", "abc"), (Spans{{0, 0}, {1, 1}, {2, 2}, {3, 3}}));
  EXPECT_EQ(matches("^", "ab\ncd"), (Spans{{0, 0}, {3, 3}}));
  EXPECT_EQ(matches("$", "a\n"), (Spans{{1, 1}, {2, 2}}));
  EXPECT_EQ(matches("\\Z", "a\n"), (Spans{{1, 1}, {2, 2}}));
}

TEST(OnigRegex, ClassesUseOnigDefinitions) {
  // \s is White_Space: U+180E is not, U+0085 and U+00A0 are.
  EXPECT_EQ(matches("\\s", "a\u180eb").size(), 0u);
  EXPECT_EQ(matches("\\s", "a\u0085b\u00a0c").size(), 2u);
  EXPECT_EQ(matches("[\\S]", "a b").size(), 2u);
  // \w covers letters, marks, all numbers and connector punctuation, but not ZWJ.
  EXPECT_EQ(matches("\\w", "a\u00b2\u216b_\u0345\u203f\u00aa\u02b0").size(), 8u);
  EXPECT_EQ(matches("\\w+", "a_b\u0301c\u200dd").size(), 2u);
  // Ruby syntax: \h is a hex digit, (?m) lets '.' match a newline.
  EXPECT_EQ(matches("\\h", "xa1 g"), (Spans{{1, 2}, {2, 3}}));
  EXPECT_EQ(matches("(?m).", "a\nb").size(), 3u);
  EXPECT_EQ(matches(".", "a\nb").size(), 2u);
  EXPECT_EQ(matches("\\d", "1\u0661\u00b2").size(), 2u);
  EXPECT_EQ(matches("(?i:'s)", "x'S y'\u017f").size(), 2u);
  // Oniguruma syntax: nested classes and class intersection.
  EXPECT_EQ(matches("[a[b]]", "abc"), (Spans{{0, 1}, {1, 2}}));
  EXPECT_EQ(matches("[a-z&&[^aeiou]]+", "robot"), (Spans{{0, 1}, {2, 3}, {4, 5}}));
}

// A String pattern is escaped the way the crate escapes it (regex::escape) before compiling.
TEST(OnigRegex, LiteralPatternsAreEscaped) {
  EXPECT_EQ(OnigRegex::literal("a.b", "test").find_all("axb a.b"), (Spans{{4, 7}}));
  EXPECT_EQ(OnigRegex::literal("[x]+(y)?", "test").find_all("xx [x]+(y)? [x]"), (Spans{{3, 11}}));
  EXPECT_EQ(OnigRegex::literal("a\nb c", "test").find_all("a\nb c"), (Spans{{0, 5}}));
  EXPECT_EQ(OnigRegex::literal("\n", "test").find_all("a\nb\n").size(), 2u);
}

// ---- Unicode coverage -----------------------------------------------------------------------------
// Code points added in Unicode 14-16, combining marks, CJK extensions, Hangul, RTL scripts, digits
// of other scripts, whitespace variants and mixed strings, with upstream's splits for several
// patterns and ids for several tokenizers (tools/oracle/unicode_fixtures.py). Rows whose characters
// are newer than the linked Oniguruma's Unicode tables are reported, not asserted: upstream bundles
// a newer Oniguruma than Debian 12 ships (see docs/tokenizers.md).

std::pair<int, int> unicode_version(const std::string& v) {
  int major = 0, minor = 0;
  std::sscanf(v.c_str(), "%d.%d", &major, &minor);
  return {major, minor};
}

std::vector<std::string> isolated_pieces(const OnigRegex& re, const std::string& s) {
  std::vector<std::string> out;
  std::size_t prev = 0;
  for (auto [b, e] : re.find_all(s)) {
    if (prev != b) out.push_back(s.substr(prev, b - prev));
    if (e != b) out.push_back(s.substr(b, e - b));
    prev = e;
  }
  if (prev != s.size()) out.push_back(s.substr(prev));
  return out;
}

TEST(UnicodeParity, SplitsAndIdsMatchTokenizers) {
  const auto lib_unicode = unicode_version(oniguruma_unicode_version());
  std::map<std::string, OnigRegex> patterns;
  std::map<std::string, Tokenizer> toks;
  int strings = 0, checks = 0, failed = 0, newer = 0, newer_differ = 0, printed = 0;
  for (const Json& row : read_jsonl(kDir / "unicode" / "expected.jsonl")) {
    if (row.contains("meta")) {
      for (const auto& [name, p] : row["meta"]["patterns"].items())
        patterns.emplace(name, OnigRegex(p.get<std::string>(), "pattern " + name));
      for (const auto& [name, d] : row["meta"]["tokenizers_dirs"].items()) {
        const fs::path dir = fs::path(TETHER_SOURCE_DIR) / d.get<std::string>();
        toks.emplace(name, fs::exists(dir / "tokenizer_config.json")
                               ? Tokenizer::from_transformers_dir(dir.string())
                               : Tokenizer::from_file((dir / "tokenizer.json").string()));
      }
      continue;
    }
    ++strings;
    const auto text = row["text"].get<std::string>();
    const bool is_newer =
        row.contains("unicode") && unicode_version(row["unicode"].get<std::string>()) > lib_unicode;
    bool differs = false;
    auto check = [&](bool ok, const std::string& what) {
      ++checks;
      if (ok) return;
      differs = true;
      if (is_newer) return;
      ++failed;
      if (printed++ < 8) ADD_FAILURE() << what << " of case " << row["i"] << " '" << escaped(text) << "'";
    };
    for (const auto& [name, expected] : row["splits"].items())
      check(isolated_pieces(patterns.at(name), text) == expected.get<std::vector<std::string>>(),
            "split " + name);
    for (const auto& [name, expected] : row["ids"].items()) {
      const auto got = toks.at(name).encode(text, /*add_special_tokens=*/false);
      check(got == expected.get<std::vector<int32_t>>(),
            "ids " + name + " (got " + ids_str(got) + ")");
    }
    newer += is_newer;
    newer_differ += is_newer && differs;
  }
  std::printf("[parity] unicode: %d strings, %d checks, %d failed; %d strings have characters newer "
              "than Oniguruma %s's Unicode %s tables, %d of them differ (not asserted)\n",
              strings, checks, failed, newer, oniguruma_version().c_str(),
              oniguruma_unicode_version().c_str(), newer_differ);
  EXPECT_GT(strings, 2000);
  EXPECT_EQ(failed, 0);
}

// encode() is const and shared across server threads: the word cache and regex scratch must cope.
TEST(Tokenizer, ConcurrentEncodeMatchesSerial) {
  const Tokenizer tok = Tokenizer::from_file((kDir / "smollm" / "tokenizer.json").string());
  const Tokenizer fresh = Tokenizer::from_file((kDir / "smollm" / "tokenizer.json").string());
  std::vector<std::vector<int32_t>> serial;
  for (const std::string& text : cases()) serial.push_back(fresh.encode(text));
  std::vector<int> mismatches(4, 0);
  std::vector<std::thread> threads;
  for (int t = 0; t < 4; ++t) {
    threads.emplace_back([&, t] {
      for (int rep = 0; rep < 3; ++rep)
        for (std::size_t i = 0; i < cases().size(); ++i)
          if (tok.encode(cases()[(i * 7 + t) % cases().size()]) !=
              serial[(i * 7 + t) % cases().size()])
            ++mismatches[t];
    });
  }
  for (auto& th : threads) th.join();
  for (int t = 0; t < 4; ++t) EXPECT_EQ(mismatches[t], 0) << "thread " << t;
}

TEST(Tokenizer, EncodeSpeed) {
  const Tokenizer tok = Tokenizer::from_file((kDir / "smollm" / "tokenizer.json").string());
  // Cold: every fixture case once on a fresh tokenizer (mostly word-cache misses).
  std::size_t bytes = 0, tokens = 0;
  auto t0 = std::chrono::steady_clock::now();
  for (const std::string& text : cases()) {
    bytes += text.size();
    tokens += tok.encode(text).size();
  }
  auto t1 = std::chrono::steady_clock::now();
  const double cold_s = std::chrono::duration<double>(t1 - t0).count();
  std::printf("[speed] cold: %zu cases, %zu bytes, %zu tokens in %.2f ms (%.1f MB/s)\n",
              cases().size(), bytes, tokens, cold_s * 1e3, bytes / cold_s / 1e6);
  // Warm: a typical task string, as the server sees it on every request.
  const std::string task = "Pick up the red cube and place it in the bowl.\n";
  const int n = 2000;
  std::size_t total = 0;
  t0 = std::chrono::steady_clock::now();
  for (int k = 0; k < n; ++k) total += tok.encode(task).size();
  t1 = std::chrono::steady_clock::now();
  const double us = std::chrono::duration<double, std::micro>(t1 - t0).count() / n;
  std::printf("[speed] warm: %zu-byte task in %.2f us (%zu tokens)\n", task.size(), us, total / n);
  EXPECT_GT(total, 0u);
}

}  // namespace
