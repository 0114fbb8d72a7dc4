// Measurement only: runs the expectations written by tools/oracle/unicode_fixtures.py (upstream
// `tokenizers` splits and ids) on each regex engine and counts the strings that differ.
// Usage: regex_measure <repo root> <expected.jsonl>...
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <string>
#include <vector>

#include "core/json_util.h"
#include "text/onig_regex.h"
#include "text/tokenizer.h"

namespace fs = std::filesystem;
using namespace tether::text;
using tether::Json;

namespace {

std::string codepoints(const std::string& s) {
  std::string out;
  for (std::size_t i = 0; i < s.size();) {
    unsigned char b = static_cast<unsigned char>(s[i]);
    std::size_t n = b < 0x80 ? 1 : b >= 0xF0 ? 4 : b >= 0xE0 ? 3 : 2;
    char32_t c = n == 1 ? b : n == 2 ? (b & 0x1F) : n == 3 ? (b & 0x0F) : (b & 0x07);
    for (std::size_t k = 1; k < n; ++k) c = (c << 6) | (static_cast<unsigned char>(s[i + k]) & 0x3F);
    char buf[16];
    std::snprintf(buf, sizeof buf, "%s%04X", out.empty() ? "" : " ", static_cast<unsigned>(c));
    out += buf;
    i += n;
  }
  return out;
}

std::vector<std::string> pieces(const OnigRegex& re, const std::string& s) {
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

}  // namespace

int main(int argc, char** argv) {
  if (argc < 3) {
    std::fprintf(stderr, "usage: %s <repo root> <expected.jsonl>...\n", argv[0]);
    return 2;
  }
  const fs::path root = argv[1];
  for (int f = 2; f < argc; ++f) {
    for (RegexEngine engine : {RegexEngine::oniguruma, RegexEngine::pcre2}) {
      detail::set_regex_engine(engine);
      const char* ename = engine == RegexEngine::oniguruma ? "oniguruma" : "pcre2";
      std::ifstream in(argv[f]);
      std::string line;
      std::map<std::string, OnigRegex> patterns;
      std::map<std::string, Tokenizer> toks;
      std::map<std::string, int> split_bad, ids_bad;
      int strings = 0, any_split = 0, any_ids = 0, printed = 0;
      while (std::getline(in, line)) {
        if (line.empty()) continue;
        const Json row = Json::parse(line);
        if (row.contains("meta")) {
          for (auto& [name, p] : row["meta"]["patterns"].items())
            patterns.emplace(name, OnigRegex(p.get<std::string>(), name));
          for (auto& [name, d] : row["meta"]["tokenizers_dirs"].items()) {
            const fs::path dir = root / d.get<std::string>();
            toks.emplace(name, fs::exists(dir / "tokenizer_config.json")
                                   ? Tokenizer::from_transformers_dir(dir.string())
                                   : Tokenizer::from_file((dir / "tokenizer.json").string()));
          }
          continue;
        }
        ++strings;
        const std::string text = row["text"].get<std::string>();
        bool sbad = false, ibad = false;
        for (auto& [name, exp] : row["splits"].items()) {
          if (!patterns.count(name)) continue;
          if (pieces(patterns.at(name), text) != exp.get<std::vector<std::string>>()) {
            ++split_bad[name];
            if (!sbad && printed++ < 6)
              std::printf("  [%s] split %s differs: %s\n", ename, name.c_str(), codepoints(text).c_str());
            sbad = true;
          }
        }
        for (auto& [name, exp] : row["ids"].items()) {
          if (!toks.count(name)) continue;
          if (toks.at(name).encode(text, false) != exp.get<std::vector<int32_t>>()) {
            ++ids_bad[name];
            if (!ibad && printed++ < 6)
              std::printf("  [%s] ids %s differ: %s\n", ename, name.c_str(), codepoints(text).c_str());
            ibad = true;
          }
        }
        if ((sbad || ibad) && std::getenv("MEASURE_DUMP"))
          std::fprintf(stderr, "%s %d %d %d\n", ename, row["i"].get<int>(), sbad ? 1 : 0, ibad ? 1 : 0);
        any_split += sbad;
        any_ids += ibad;
      }
      std::printf("%s %s: %d strings; strings with a split mismatch %d, with an id mismatch %d\n",
                  argv[f], ename, strings, any_split, any_ids);
      std::printf("  splits:");
      for (auto& [name, _] : patterns) std::printf(" %s=%d", name.c_str(), split_bad[name]);
      std::printf("\n  ids:");
      for (auto& [name, _] : toks) std::printf(" %s=%d", name.c_str(), ids_bad[name]);
      std::printf("\n");
      std::fflush(stdout);
    }
  }
  return 0;
}
