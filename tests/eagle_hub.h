// GR00T N1.6 checkpoints name Isaac-GR00T's vendored Eagle directory (`nvidia/Eagle-Block2A-2B-v2`), which Tether
// finds beside the checkpoint or in the hub cache. The N1.6 fixture's stand-in (tests/fixtures/gr00t_n16/eagle) is put
// in a scratch hub cache under that id; tests point HF_HUB_CACHE at the returned directory.
#pragma once

#include <filesystem>
#include <fstream>

#include "scratch_dir.h"

namespace tether::testing {

// `as_released`: the directory as Isaac-GR00T ships it, whose tokenizer is vocab.json + merges.txt with no
// tokenizer.json (the stand-in has both, as transformers saves them).
inline std::filesystem::path eagle_hub_cache(bool as_released = false) {
  namespace fs = std::filesystem;
  const fs::path hub = scratch_dir() / (as_released ? "eagle_hub_as_released" : "eagle_hub");
  const fs::path repo = hub / "models--nvidia--Eagle-Block2A-2B-v2";
  fs::create_directories(repo / "snapshots");
  fs::create_directories(repo / "refs");
  std::ofstream(repo / "refs" / "main") << "main";
  const fs::path snapshot = repo / "snapshots" / "main";
  const fs::path standin = fs::path(TETHER_FIXTURES_DIR) / "gr00t_n16" / "eagle";
  if (fs::exists(snapshot)) return hub;
  if (!as_released) {
    fs::create_directory_symlink(standin, snapshot);
    return hub;
  }
  fs::create_directory(snapshot);
  for (const auto& e : fs::directory_iterator(standin))
    if (e.path().filename() != "tokenizer.json") fs::copy_file(e.path(), snapshot / e.path().filename());
  return hub;
}

}  // namespace tether::testing
