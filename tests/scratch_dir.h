// One scratch folder per test process under the system's temp directory, removed when the process exits, so that a
// test run leaves nothing behind in /tmp. Tests name their files and folders inside it.
#pragma once

#include <unistd.h>

#include <filesystem>
#include <string>
#include <system_error>

namespace tether::testing {

inline const std::filesystem::path& scratch_dir() {
  struct Dir {
    std::filesystem::path path =
        std::filesystem::temp_directory_path() / ("tether_test_" + std::to_string(::getpid()));
    ~Dir() {
      std::error_code ignored;
      std::filesystem::remove_all(path, ignored);
    }
  };
  static Dir dir;
  std::filesystem::create_directories(dir.path);
  return dir.path;
}

}  // namespace tether::testing
