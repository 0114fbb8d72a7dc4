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
#include "cli/registry.h"
#include "core/json_util.h"
#include "hub/hub_client.h"
#include "models/model.h"

namespace tether::cli {

namespace fs = std::filesystem;

namespace {

// The checkpoint directory for `id`, or an Error (exit 2) saying exactly what is missing and what to do.
std::string resolve_model(const Registry& reg, const std::string& id) {
  const RegistryEntry& e = reg.get(id);
  if (!e.supported)
    throw Error(ErrorCode::unsupported, "--model " + id + ": the " + e.family +
                                            " family is not supported by this Tether build yet (supported: smolvla)");
  if (auto dir = local_checkpoint(e)) return *dir;
  if (!e.bundled_dir.empty())
    throw Error(ErrorCode::not_found, "--model " + id + ": bundled checkpoint " + e.bundled_dir + " is missing");
  throw Error(ErrorCode::not_found, "--model " + id + ": " + e.hf_repo + " is not in the Hugging Face cache (" +
                                        hub::HubClient::from_env().cache().root() + "); download it with `tether models pull " +
                                        id + "`");
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
            const Registry reg = Registry::load();
            if (args->list) return list_models(reg, false);
            if (args->model.empty()) throw Error(ErrorCode::invalid_argument, "--model is required (see tether go --list)");
            const std::string dir = resolve_model(reg, args->model);
            std::fprintf(stderr, "tether go: %s -> %s\n", args->model.c_str(), dir.c_str());
            return run_server(dir, args->flags);
          }};
}

}  // namespace tether::cli
