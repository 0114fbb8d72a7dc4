// `tether models list|info|pull`: the registry shipped with Tether and downloads from the Hugging Face hub into
// its shared cache.
#include <cstdio>
#include <filesystem>
#include <iostream>

#include "cli/commands.h"
#include "cli/registry.h"
#include "hub/hub_client.h"

namespace tether::cli {

namespace fs = std::filesystem;

namespace {

std::string size_str(double bytes) {
  char buf[32];
  if (bytes >= 1e9) std::snprintf(buf, sizeof buf, "%.1f GB", bytes / 1e9);
  else std::snprintf(buf, sizeof buf, "%.0f MB", bytes / 1e6);
  return buf;
}

std::string params_str(const std::optional<int64_t>& p) {
  if (!p) return "?";
  char buf[32];
  if (*p >= 1000000000) std::snprintf(buf, sizeof buf, "%.1fB", double(*p) / 1e9);
  else if (*p >= 1000000) std::snprintf(buf, sizeof buf, "%.0fM", double(*p) / 1e6);
  else std::snprintf(buf, sizeof buf, "%.0fK", double(*p) / 1e3);
  return buf;
}

// Whether the model fits a deployment target and at which precision: the target's default if it fits, else the
// smallest of its precisions that does.
Json fit_on_target(const RegistryEntry& e, const Json& target) {
  Json out = {{"target", target.value("id", "")}};
  if (!e.parameters) {
    out["fits"] = nullptr;
    out["reason"] = "parameter count unknown";
    return out;
  }
  const double budget = double(target.value("memory_gb", 0)) * 1e9 * 0.8;  // leave room for the OS and the robot stack
  std::vector<std::string> order = {target.value("default_precision", "fp32")};
  for (const auto& p : target.value("precisions", Json::array()))
    if (p.get<std::string>() != order.front()) order.push_back(p.get<std::string>());
  for (const auto& p : order) {
    if (memory_needed_bytes(*e.parameters, p) <= budget) {
      out["fits"] = true;
      out["precision"] = p;
      out["memory"] = size_str(memory_needed_bytes(*e.parameters, p));
      return out;
    }
  }
  out["fits"] = false;
  out["reason"] = "needs " + size_str(memory_needed_bytes(*e.parameters, "bf16")) + " in bf16, the target offers " +
                  size_str(budget);
  return out;
}

Json figures_json(const RegistryEntry& e) {
  Json out = Json::array();
  for (const auto& f : e.figures)
    out.push_back({{"benchmark", f.benchmark},
                   {"metric", f.metric},
                   {"value", f.value},
                   {"setting", f.setting},
                   {"source", {{"title", f.source_title}, {"url", f.source_url}}}});
  return out;
}

Json entry_json(const RegistryEntry& e, const Json& all_targets) {
  Json disk = Json::object();
  if (e.parameters)
    for (const char* p : {"fp32", "bf16", "fp16"}) disk[p] = size_str(double(*e.parameters) * (std::string(p) == "fp32" ? 4 : 2));
  const auto local = local_checkpoint(e);
  Json targets = Json::array();
  for (const auto& t : all_targets) targets.push_back(fit_on_target(e, t));
  return {{"id", e.id},
          {"family", e.family},
          {"hf_repo", e.hf_repo.empty() ? Json(nullptr) : Json(e.hf_repo)},
          {"subfolder", e.subfolder.empty() ? Json(nullptr) : Json(e.subfolder)},
          {"parameters", e.parameters ? Json(*e.parameters) : Json(nullptr)},
          {"license", e.license},
          {"supported", e.supported},
          {"description", e.description},
          {"disk_size", disk},
          {"local_path", local ? Json(*local) : Json(nullptr)},
          {"published", e.figures.empty() ? Json(nullptr) : Json(headline_figure(e))},
          {"figures", figures_json(e)},
          {"figures_note", e.figures_note.empty() ? Json(nullptr) : Json(e.figures_note)},
          {"targets", targets}};
}

struct ModelsArgs {
  std::string id, target, revision = "main";
  bool json = false;
};

int run_info(const ModelsArgs& a) {
  const Registry reg = Registry::load();
  const RegistryEntry& e = reg.get(a.id);
  const Json info = entry_json(e, a.target.empty() ? deployment_targets() : Json::array({deployment_target(a.target)}));
  if (a.json) {
    std::cout << info.dump(2) << "\n";
    return kExitOk;
  }
  for (const char* k : {"id", "family", "hf_repo", "subfolder", "parameters", "license", "supported", "description",
                        "disk_size", "local_path"}) {
    if (std::string(k) == "subfolder" && info[k].is_null()) continue;
    std::printf("%-12s %s\n", k, info[k].is_string() ? info[k].get<std::string>().c_str() : info[k].dump().c_str());
  }
  for (const auto& f : e.figures) {
    std::string metric = f.metric;  // the value already carries the unit
    if (const auto unit = metric.find(" (%)"); unit != std::string::npos) metric.erase(unit, 4);
    std::printf("%-12s %s: %s %s \u2014 %s\n", "published", f.benchmark.c_str(), figure_value(f).c_str(),
                metric.c_str(), f.setting.c_str());
    std::printf("%-12s source: %s, %s\n", "", f.source_title.c_str(), f.source_url.c_str());
  }
  if (!e.figures_note.empty())
    std::printf("%-12s %s%s\n", "published", e.figures.empty() ? "none: " : "note: ", e.figures_note.c_str());
  for (const auto& t : info["targets"]) {
    const std::string tid = t["target"];
    if (t["fits"].is_null()) std::printf("%-12s %s: %s\n", "target", tid.c_str(), t["reason"].get<std::string>().c_str());
    else if (t["fits"].get<bool>())
      std::printf("%-12s %s: fits in %s (%s)\n", "target", tid.c_str(), t["precision"].get<std::string>().c_str(),
                  t["memory"].get<std::string>().c_str());
    else std::printf("%-12s %s: does not fit (%s)\n", "target", tid.c_str(), t["reason"].get<std::string>().c_str());
  }
  return kExitOk;
}

}  // namespace

int list_models(const Registry& reg, bool json) {
  if (json) {
    Json arr = Json::array();
    const Json targets = deployment_targets();
    for (const auto& e : reg.entries()) arr.push_back(entry_json(e, targets));
    std::cout << arr.dump(2) << "\n";
    return kExitOk;
  }
  const char* row = "%-22s %-12s %-30s %7s %-10s %-6s %-16s %s\n";
  std::printf(row, "id", "family", "source", "params", "tether", "local", "published", "license");
  for (const auto& e : reg.entries())
    std::printf(row, e.id.c_str(), e.family.c_str(), e.hf_repo.empty() ? "(bundled)" : e.hf_repo.c_str(),
                params_str(e.parameters).c_str(), e.supported ? "supported" : "not yet",
                local_checkpoint(e) ? "yes" : "no", headline_figure(e).c_str(), e.license.c_str());
  return kExitOk;
}

namespace {

int run_pull(const ModelsArgs& a) {
  const Registry reg = Registry::load();
  const RegistryEntry& e = reg.get(a.id);
  if (!e.bundled_dir.empty()) {
    std::printf("%s is bundled with Tether: %s\n", e.id.c_str(), e.bundled_dir.c_str());
    return kExitOk;
  }
  std::printf("%s\n", pull_model(e, a.revision).c_str());
  return kExitOk;
}

}  // namespace

std::string pull_model(const RegistryEntry& e, const std::string& revision) {
  if (!e.bundled_dir.empty()) return e.bundled_dir;
  hub::HubClient hub = hub::HubClient::from_env();
  for (const auto& req : e.requires_repos) {
    std::fprintf(stderr, "pulling %s (needed by %s)\n", req.repo.c_str(), e.id.c_str());
    hub.snapshot_download(req.repo, "main", req.patterns);
  }
  std::fprintf(stderr, "pulling %s @ %s\n", e.hf_repo.c_str(), revision.c_str());
  if (e.subfolder.empty()) return hub.snapshot_download(e.hf_repo, revision, e.patterns);
  // Only the entry's folder of a repo that holds several checkpoints.
  const std::vector<std::string> patterns = e.patterns.empty() ? std::vector<std::string>{e.subfolder + "/"} : e.patterns;
  return (fs::path(hub.snapshot_download(e.hf_repo, revision, patterns)) / e.subfolder).string();
}

Verb add_models(CLI::App& app) {
  auto args = std::make_shared<ModelsArgs>();
  CLI::App* sub = app.add_subcommand("models", "The model registry: list, info, pull");
  sub->require_subcommand(1);
  CLI::App* list = sub->add_subcommand("list", "Models Tether knows: size, whether they are on disk, headline published figure");
  list->add_flag("--json", args->json, "Print JSON");
  CLI::App* info = sub->add_subcommand("info", "One model: sources, sizes per precision, published figures, which targets it fits");
  info->add_option("id", args->id, "Registry id")->required();
  info->add_option("--target", args->target, "Only this deployment target (see tether inspect targets)");
  info->add_flag("--json", args->json, "Print JSON");
  CLI::App* pull = sub->add_subcommand("pull", "Download a model into the Hugging Face cache (HF_HOME, HF_TOKEN, HF_ENDPOINT)");
  pull->add_option("id", args->id, "Registry id")->required();
  pull->add_option("--revision", args->revision, "Branch, tag or commit")->capture_default_str();
  return {sub, [args, list, info] {
            if (list->parsed()) return list_models(Registry::load(), args->json);
            if (info->parsed()) return run_info(*args);
            return run_pull(*args);
          }};
}

}  // namespace tether::cli
