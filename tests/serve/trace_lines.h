// The trace lines a test server wrote under its --record directory, for the serve tests that check them.
#pragma once

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "core/json_util.h"

namespace tether::serve::testing {

// Every line of every trace file in `dir`, files in name order (the recorder numbers them in writing order).
inline std::vector<Json> read_trace_lines(const std::filesystem::path& dir) {
  std::vector<std::filesystem::path> files;
  for (const auto& entry : std::filesystem::directory_iterator(dir)) files.push_back(entry.path());
  std::sort(files.begin(), files.end());
  std::vector<Json> lines;
  for (const auto& file : files) {
    std::ifstream in(file);
    for (std::string line; std::getline(in, line);)
      if (!line.empty()) lines.push_back(Json::parse(line));
  }
  return lines;
}

}  // namespace tether::serve::testing
