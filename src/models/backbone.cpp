// Locating a policy's backbone files: relative to the checkpoint, an absolute path, or the local hub cache.
#include "models/backbone.h"

#include <fstream>

#include "core/error.h"
#include "core/hf_paths.h"

namespace tether::models {

namespace fs = std::filesystem;

fs::path find_backbone_dir(const fs::path& checkpoint_dir, const std::string& name, const std::string& named_by) {
  std::vector<fs::path> tried;
  auto usable = [&](const fs::path& p) {
    tried.push_back(p);
    return fs::is_regular_file(p / "config.json");
  };
  if (usable(checkpoint_dir / name)) return checkpoint_dir / name;
  if (fs::path(name).is_absolute() && usable(name)) return name;
  if (name.find('/') != std::string::npos && !fs::path(name).is_absolute()) {
    std::string repo = "models--";
    for (char c : name) repo += c == '/' ? std::string("--") : std::string(1, c);
    const fs::path repo_dir = fs::path(hf_hub_cache()) / repo;
    std::string revision = "main";
    if (std::ifstream ref(repo_dir / "refs" / "main"); ref) std::getline(ref, revision);
    if (usable(repo_dir / "snapshots" / revision)) return repo_dir / "snapshots" / revision;
  }
  std::string where;
  for (const auto& p : tried) where += (where.empty() ? "" : ", ") + p.string();
  throw Error(ErrorCode::not_found, "'" + name + "' (" + named_by + " of " + checkpoint_dir.string() +
                                        ") not found: no config.json in " + where +
                                        " (tether models pull fetches it with the checkpoint)");
}

std::vector<std::string> backbone_files(const fs::path& dir) {
  std::vector<std::string> out;
  for (const char* f : {"config.json", "tokenizer.json", "tokenizer_config.json", "special_tokens_map.json",
                        "added_tokens.json", "vocab.json", "merges.txt", "tokenizer.model", "processor_config.json",
                        "preprocessor_config.json", "chat_template.json"})
    if (fs::is_regular_file(dir / f)) out.push_back(f);
  return out;
}

bool vlm_keeps_copy(const std::string& tensor) {
  const auto ends_with = [&](const std::string& s) {
    return tensor.size() >= s.size() && tensor.compare(tensor.size() - s.size(), s.size(), s) == 0;
  };
  return !ends_with("lm_head.weight") && !ends_with("embed_tokens.weight") && !ends_with("language_model.norm.weight");
}

}  // namespace tether::models
