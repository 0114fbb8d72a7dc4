// GR00T N1.6 checkpoints name Isaac-GR00T's vendored Eagle directory (`nvidia/Eagle-Block2A-2B-v2`), which Tether
// finds beside the checkpoint or in the hub cache. The N1.6 fixture's stand-in (tests/fixtures/gr00t_n16/eagle) is put
// in a scratch hub cache under that id; tests point HF_HUB_CACHE at the returned directory.
#pragma once

#include <filesystem>
#include <fstream>

#include "scratch_dir.h"

namespace tether::testing {

inline std::filesystem::path eagle_hub_cache() {
  namespace fs = std::filesystem;
  const fs::path hub = scratch_dir() / "eagle_hub";
  const fs::path repo = hub / "models--nvidia--Eagle-Block2A-2B-v2";
  fs::create_directories(repo / "snapshots");
  fs::create_directories(repo / "refs");
  std::ofstream(repo / "refs" / "main") << "main";
  const fs::path snapshot = repo / "snapshots" / "main";
  if (!fs::exists(snapshot))
    fs::create_directory_symlink(fs::path(TETHER_FIXTURES_DIR) / "gr00t_n16" / "eagle", snapshot);
  return hub;
}

}  // namespace tether::testing
