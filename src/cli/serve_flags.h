// Flags shared by `tether serve` and `tether go` (the server's limits), and running the server once a checkpoint
// directory is known.
#pragma once

#include <CLI/CLI.hpp>
#include <string>

#include "serve/server.h"

namespace tether::cli {

struct ServeFlags {
  serve::ServerOptions options;
  std::string api_key_file;
  std::string precision = "fp32";
};

void add_serve_flags(CLI::App* sub, ServeFlags& flags);
// Resolves the API key (file, else TETHER_API_KEY), binds, prints the listening line, serves until SIGTERM/SIGINT.
int run_server(const std::string& checkpoint_dir, const ServeFlags& flags);

}  // namespace tether::cli
