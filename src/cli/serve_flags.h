// Flags shared by `tether serve` and `tether go` (the server's limits), and running the server once a checkpoint
// directory is known.
#pragma once

#include <CLI/CLI.hpp>
#include <map>
#include <string>
#include <vector>

#include "serve/server.h"

namespace tether::cli {

// Relative velocity change under which --adaptive-steps stops when no --adaptive-threshold is given.
inline constexpr float kDefaultAdaptiveThreshold = 0.05f;

struct ServeFlags {
  serve::ServerOptions options;
  std::string api_key_file;
  std::string precision = "fp32";
  std::string backend = "cpu";  // --backend; `tether go` starts from auto
  // GR00T: the embodiments served (--embodiment-tag, repeatable or comma-separated); the first is the default, a
  // request names another by its tag. Empty: the checkpoint's only one.
  std::vector<std::string> embodiment_tags;
  // Robot-side wedge flags (--embodiment, --custom-embodiment-config, --safety-config): each entry is a value for
  // every embodiment served, or TAG=VALUE for the one embodiment TAG (a GR00T server driving several robots). An
  // embodiment's own entry wins over the shared one.
  std::vector<std::string> embodiment, custom_embodiment, safety_config;
  // Other wedge flags that name files or choices. run_server turns all of them into wedge options before the socket
  // is bound, so a bad file is an error at start-up.
  std::string fallback_api_key_file, rtc_schedule = "linear";
  // --openpi-layout entries, VALUE or TAG=VALUE the same way (each robot's client sends its own keys).
  std::vector<std::string> openpi_layouts;
  bool adaptive_steps = false;
  float adaptive_threshold = -1;  // < 0: not given (kDefaultAdaptiveThreshold with --adaptive-steps)
  std::string record_dir, record_images = "hash", record_fsync = "interval";
  std::uint64_t record_max_bytes = 64ull << 20;
};

void add_serve_flags(CLI::App* sub, ServeFlags& flags);
// The --openpi-* flags (openpi_flags.cpp); add_serve_flags adds them.
void add_openpi_flags(CLI::App* sub, ServeFlags& flags);

// A flag's entries split by embodiment: an entry is TAG=VALUE when the text before its first '=' is one of `tags`,
// else a value shared by every embodiment. Throws on a value given twice for one embodiment (or twice shared) and on
// an apparent TAG= that is neither a served tag nor, when `is_file`, an existing path (a mistyped tag).
struct PerEmbodiment {
  std::string shared;                       // empty: none
  std::map<std::string, std::string> own;  // by tag
};
PerEmbodiment per_embodiment(const std::vector<std::string>& entries, const std::vector<std::string>& tags,
                             const char* flag, bool is_file);
// The embodiment file an export carries; `tether serve` on such a directory uses it unless a flag names another.
inline constexpr const char* kExportEmbodimentFile = "embodiment.json";
// Path of the preset models/embodiments/<name>.json after validating it (not_found listing the presets otherwise).
std::string embodiment_preset_file(const std::string& name);
// Loads the embodiment / safety / key files the wedge flags name for the embodiment `tag` (empty: the only one
// served), or the checkpoint's own embodiment.json; throws tether::Error naming the flag or field.
runtime::WedgeOptions wedge_options(const ServeFlags& flags, const std::string& checkpoint_dir,
                                    const std::string& tag = "");
// Resolves the API key (file, else TETHER_API_KEY), binds, prints the listening line, serves until SIGTERM/SIGINT.
int run_server(const std::string& checkpoint_dir, const ServeFlags& flags);

}  // namespace tether::cli
