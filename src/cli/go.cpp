// `tether go --model <id>`: serve a model by its registry name. Probes the machine (CPU, memory, GPU), looks the id up
// in models/registry.json, finds the checkpoint (bundled, or the Hugging Face cache; pulled when missing), exports it
// at the chosen precision into the Tether cache and serves it with the same flags as `tether serve`.
#include <cstdio>
#include <cstdlib>
#include <filesystem>

#include "cli/commands.h"
#include "cli/hardware.h"
#include "cli/serve_flags.h"
#include "cli/registry.h"
#include "core/json_util.h"
#include "models/family.h"

namespace tether::cli {

namespace fs = std::filesystem;

namespace {

std::string supported_families() {
  std::string out;
  for (const auto& f : models::model_families()) out += (out.empty() ? "" : ", ") + f;
  return out;
}

fs::path tether_cache() {
  if (const char* v = std::getenv("TETHER_CACHE"); v && *v) return v;
  const char* home = std::getenv("HOME");
  return fs::path(home ? home : "/") / ".cache" / "tether";
}

// The export for (model, precision, embodiment tag) under the Tether cache, rebuilt when it is missing, made by another Tether
// version, or made from another source.
std::string cached_export(const RegistryEntry& e, const std::string& src, const std::string& precision,
                          const std::string& embodiment_tag) {
  const fs::path dir = tether_cache() / "exports" / TETHER_VERSION /
                       (e.id + "-" + precision + (embodiment_tag.empty() ? "" : "-" + embodiment_tag));
  const fs::path manifest = dir / "tether_export.json";
  if (fs::exists(manifest)) {
    const Json m = read_json_file(manifest.string());
    const std::string source = m.value("source", Json::object()).value("path", "");
    if (m.value("tether_version", "") == TETHER_VERSION && source == fs::absolute(src).lexically_normal().string() &&
        m.value("precision", "") == precision &&
        m.value("embodiment_tag", Json(nullptr)) == (embodiment_tag.empty() ? Json(nullptr) : Json(embodiment_tag))) {
      std::fprintf(stderr, "tether go: using the export in %s\n", dir.string().c_str());
      return dir.string();
    }
  }
  std::fprintf(stderr, "tether go: exporting %s (%s) to %s\n", e.id.c_str(), precision.c_str(), dir.string().c_str());
  fs::remove_all(dir);
  const double worst = export_checkpoint(src, dir.string(), precision, "", "", embodiment_tag);
  std::fprintf(stderr, "tether go: export verified, max |diff| against the source %.3e (receipt: %s)\n", worst,
               (dir / "VERIFICATION.md").string().c_str());
  return dir.string();
}

}  // namespace

Verb add_go(CLI::App& app) {
  struct Args {
    std::string model;
    bool list = false;
    ServeFlags flags;
  };
  auto args = std::make_shared<Args>();
  args->flags.backend = "auto";  // the GPU when there is a usable one
  CLI::App* sub = app.add_subcommand(
      "go", "Probe this machine, pull the model if missing, export it (cached per Tether version) and serve it");
  sub->add_option("--model", args->model, "Registry id, e.g. smolvla-demo or smolvla-base");
  sub->add_flag("--list", args->list, "List the registry's models and exit");
  add_serve_flags(sub, args->flags);
  return {sub, [args, sub] {
            const Registry reg = Registry::load();
            if (args->list) return list_models(reg, false);
            if (args->model.empty()) throw Error(ErrorCode::invalid_argument, "--model is required (see tether go --list)");
            const RegistryEntry& e = reg.get(args->model);
            // The export holds one embodiment's statistics (cached per tag): several are served from the checkpoint.
            if (args->flags.embodiment_tags.size() > 1)
              throw Error(ErrorCode::invalid_argument,
                          "go serves one --embodiment-tag; serve several from the checkpoint with `tether serve "
                          "<checkpoint> --embodiment-tag a,b`");
            // The probe comes first: what this machine offers decides the precision and where the model runs.
            const MachineProbe machine = probe_machine();
            std::fprintf(stderr, "tether go: %s\ntether go: %s\n", cpu_summary(machine).c_str(),
                         gpu_summary(machine.gpu).c_str());
            if (!e.supported)
              throw Error(ErrorCode::unsupported, "--model " + e.id + ": the " + e.family +
                                                      " family is not supported by this Tether build yet (supported: " + supported_families() + ")");
            const PrecisionChoice choice = choose_precision(
                machine, e.id, e.parameters, sub->get_option("--precision")->count() ? args->flags.precision : "");
            std::fprintf(stderr, "tether go: %s\n", choice.reason.c_str());
            std::optional<std::string> src = local_checkpoint(e);
            if (!src) {
              if (!e.bundled_dir.empty())
                throw Error(ErrorCode::not_found, "--model " + e.id + ": bundled checkpoint " + e.bundled_dir + " is missing");
              std::fprintf(stderr, "tether go: %s is not on disk: pulling it\n", e.id.c_str());
              try {
                src = pull_model(e);
              } catch (const Error& err) {
                throw Error(err.code(), "--model " + e.id + ": " + e.hf_repo +
                                            " is not on disk and could not be downloaded (" + err.what() +
                                            "); retry with network access or `tether models pull " + e.id + "`");
              }
            }
            ServeFlags flags = args->flags;
            flags.precision = choice.precision;
            // KServe's model name: the registry id, not the export directory's name.
            if (flags.options.model_name.empty()) flags.options.model_name = e.id;
            const std::string tag = flags.embodiment_tags.empty() ? "" : flags.embodiment_tags.front();
            const std::string dir = cached_export(e, *src, flags.precision, tag);
            std::fprintf(stderr, "tether go: %s -> %s (%s)\n", e.id.c_str(), dir.c_str(), flags.precision.c_str());
            return run_server(dir, flags);
          }};
}

}  // namespace tether::cli
