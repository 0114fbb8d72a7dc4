// `tether go --model <id>`: serve a model by its registry name. The id is looked up in models/registry.json, the
// checkpoint found locally (bundled, or the Hugging Face cache), and served with the same flags as `tether serve`.
#include <algorithm>
#include <cctype>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iostream>

#include "cli/commands.h"
#include "cli/serve_flags.h"
#include "core/json_util.h"
#include "hub/hub_client.h"
#include "models/model.h"

namespace tether::cli {

namespace fs = std::filesystem;

namespace {

fs::path registry_path() {
  if (const char* env = std::getenv("TETHER_REGISTRY"); env && *env) return env;
  return fs::path(TETHER_SOURCE_DIR) / "models" / "registry.json";
}

Json load_registry() {
  const fs::path path = registry_path();
  if (!fs::exists(path))
    throw Error(ErrorCode::not_found, path.string() + ": model registry not found (set TETHER_REGISTRY to its path)");
  const Json reg = read_json_file(path.string());
  if (!reg.contains("models") || !reg["models"].is_object())
    throw Error(ErrorCode::format, path.string() + ": no 'models' object");
  return reg;
}

int list_models(const Json& reg) {
  const auto families = models::model_families();
  for (auto it = reg["models"].begin(); it != reg["models"].end(); ++it) {
    const Json& m = it.value();
    const std::string family = m.value("family", "?");
    const bool supported = m.value("supported", false) &&
                           std::find(families.begin(), families.end(), family) != families.end();
    std::printf("%-14s %-8s %-24s %-10s %s\n", it.key().c_str(), family.c_str(),
                m.value("hf_repo", std::string("(bundled)")).c_str(), supported ? "supported" : "not yet",
                m.value("license", std::string("?")).c_str());
  }
  return kExitOk;
}

// The checkpoint directory for `id`, or an Error (exit 2) saying exactly what is missing and what to do.
std::string resolve_model(const Json& reg, const std::string& id) {
  const fs::path path = registry_path();
  const auto& models_json = reg["models"];
  if (!models_json.contains(id)) {
    std::string known;
    for (auto it = models_json.begin(); it != models_json.end(); ++it) known += (known.empty() ? "" : ", ") + it.key();
    throw Error(ErrorCode::invalid_argument, "--model " + id + ": not in the registry " + path.string() + " (known: " + known + ")");
  }
  const Json& m = models_json[id];
  const std::string where = path.string() + ": models." + id;
  const std::string family = json_get<std::string>(m, "family", where);
  const auto families = models::model_families();
  if (!m.value("supported", false) || std::find(families.begin(), families.end(), family) == families.end())
    throw Error(ErrorCode::unsupported, "--model " + id + ": the " + family +
                                            " family is not supported by this Tether build yet (supported: smolvla)");
  if (m.contains("path")) {
    fs::path dir = json_get<std::string>(m, "path", where);
    if (dir.is_relative()) dir = path.parent_path() / dir;
    if (!fs::is_directory(dir)) throw Error(ErrorCode::not_found, "--model " + id + ": bundled checkpoint " + dir.string() + " is missing");
    return dir.string();
  }
  const std::string repo = json_get<std::string>(m, "hf_repo", where);
  const hub::HubClient hub = hub::HubClient::from_env();
  if (auto dir = hub.cached_snapshot(repo)) return *dir;
  throw Error(ErrorCode::not_found, "--model " + id + ": " + repo + " is not in the Hugging Face cache (" +
                                        hub.cache().root() + "); download it with `huggingface-cli download " +
                                        repo + "` (`tether models pull` comes later)");
}

}  // namespace

Verb add_go(CLI::App& app) {
  struct Args {
    std::string model;
    bool list = false;
    ServeFlags flags;
  };
  auto args = std::make_shared<Args>();
  CLI::App* sub = app.add_subcommand("go", "Serve a model by name from the registry (see --list)");
  sub->add_option("--model", args->model, "Registry id, e.g. smolvla-demo or smolvla-base");
  sub->add_flag("--list", args->list, "List the registry's models and exit");
  add_serve_flags(sub, args->flags);
  return {sub, [args] {
            const Json reg = load_registry();
            if (args->list) return list_models(reg);
            if (args->model.empty()) throw Error(ErrorCode::invalid_argument, "--model is required (see tether go --list)");
            const std::string dir = resolve_model(reg, args->model);
            std::fprintf(stderr, "tether go: %s -> %s\n", args->model.c_str(), dir.c_str());
            return run_server(dir, args->flags);
          }};
}

}  // namespace tether::cli
