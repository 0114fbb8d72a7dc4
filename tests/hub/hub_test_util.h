// Shared helpers for the hub tests: scratch directories, file I/O and a scoped environment
// variable.
#pragma once

#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <optional>
#include <string>

#include "hub/hash.h"
#include "scratch_dir.h"

namespace tether::hub::test {

namespace fs = std::filesystem;

// A fresh directory per test, removed afterwards.
class ScratchDir {
 public:
  explicit ScratchDir(const std::string& name) {
    static int counter = 0;
    path_ = tether::testing::scratch_dir() / ("hub_" + std::to_string(counter++) + "_" + name);
    fs::remove_all(path_);
    fs::create_directories(path_);
  }
  ~ScratchDir() {
    std::error_code ec;
    fs::remove_all(path_, ec);
  }
  std::string str() const { return path_.string(); }
  const fs::path& path() const { return path_; }

 private:
  fs::path path_;
};

inline std::string read_file(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  return std::string((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
}

inline void write_file(const fs::path& p, const std::string& data) {
  fs::create_directories(p.parent_path());
  std::ofstream out(p, std::ios::binary | std::ios::trunc);
  out << data;
}

// Sets (or unsets, with nullopt) an environment variable for the lifetime of the object.
class ScopedEnv {
 public:
  ScopedEnv(const char* name, std::optional<std::string> value) : name_(name) {
    if (const char* old = std::getenv(name)) old_ = old;
    if (value)
      ::setenv(name, value->c_str(), 1);
    else
      ::unsetenv(name);
  }
  ~ScopedEnv() {
    if (old_)
      ::setenv(name_.c_str(), old_->c_str(), 1);
    else
      ::unsetenv(name_.c_str());
  }

 private:
  std::string name_;
  std::optional<std::string> old_;
};

// The same deterministic bytes fake_hub.py serves (its pattern_bytes): sha256("<seed>:<i>")
// digests, concatenated.
inline std::string pattern_bytes(size_t n, int seed) {
  std::string out;
  for (size_t i = 0; out.size() < n; ++i) {
    std::string hex = sha256_hex(std::to_string(seed) + ":" + std::to_string(i));
    for (size_t k = 0; k < hex.size(); k += 2)
      out += static_cast<char>(std::stoi(hex.substr(k, 2), nullptr, 16));
  }
  out.resize(n);
  return out;
}

}  // namespace tether::hub::test
