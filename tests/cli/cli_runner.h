// Runs the real `tether` binary the way a user would and captures its exit code, stdout and stderr.
#pragma once

#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include "scratch_dir.h"

// TETHER_MAX_CPU_ISA values below what this CPU may have, lowest first; the first has no bf16 instructions.
#if defined(__x86_64__)
inline constexpr const char* kLowerIsaCaps[] = {"AVX2", "AVX512_CORE"};
#else
inline constexpr const char* kLowerIsaCaps[] = {"NEON"};
#endif

struct CliRun {
  int code = -1;
  std::string out, err;
};

// `args` are already shell-quoted.
inline CliRun run_tether(const std::string& args) {
  const std::filesystem::path err_file =
      tether::testing::scratch_dir() / "cli_err";
  const std::string cmd = std::string(TETHER_BINARY) + " " + args + " 2>" + err_file.string();
  CliRun r;
  FILE* pipe = popen(cmd.c_str(), "r");
  std::array<char, 4096> buf{};
  std::size_t n;
  while ((n = fread(buf.data(), 1, buf.size(), pipe)) > 0) r.out.append(buf.data(), n);
  const int status = pclose(pipe);
  r.code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  {
    std::ifstream in(err_file);
    r.err.assign(std::istreambuf_iterator<char>(in), {});
  }
  std::error_code ignored;
  std::filesystem::remove(err_file, ignored);
  return r;
}
