#include "cli/registry.h"

#include <algorithm>
#include <cstdlib>
#include <filesystem>
#include <fstream>

#include "cli/commands.h"

#include "hub/hub_client.h"
#include "models/model.h"

namespace tether::cli {

namespace fs = std::filesystem;

Registry Registry::load() {
  Registry r;
  const char* env = std::getenv("TETHER_REGISTRY");
  r.path_ = env && *env ? std::string(env) : (fs::path(TETHER_SOURCE_DIR) / "models" / "registry.json").string();
  if (!fs::exists(r.path_))
    throw Error(ErrorCode::not_found, r.path_ + ": model registry not found (set TETHER_REGISTRY to its path)");
  const Json reg = read_json_file(r.path_);
  if (!reg.contains("models") || !reg["models"].is_object())
    throw Error(ErrorCode::format, r.path_ + ": no 'models' object");
  const auto families = models::model_families();
  for (auto it = reg["models"].begin(); it != reg["models"].end(); ++it) {
    const Json& m = it.value();
    const std::string where = r.path_ + ": models." + it.key();
    RegistryEntry e;
    e.id = it.key();
    e.family = json_get<std::string>(m, "family", where);
    e.description = json_get_or<std::string>(m, "description", "", where);
    e.license = json_get_or<std::string>(m, "license", "?", where);
    e.hf_repo = json_get_or<std::string>(m, "hf_repo", "", where);
    if (m.contains("path")) {
      fs::path dir = json_get<std::string>(m, "path", where);
      if (dir.is_relative()) dir = fs::path(r.path_).parent_path() / dir;
      e.bundled_dir = dir.lexically_normal().string();
    }
    if (e.hf_repo.empty() == e.bundled_dir.empty())
      throw Error(ErrorCode::format, where + ": give exactly one of 'hf_repo' and 'path'");
    if (m.contains("parameters") && !m["parameters"].is_null()) e.parameters = json_get<int64_t>(m, "parameters", where);
    e.supported = json_get_or<bool>(m, "supported", false, where) &&
                  std::find(families.begin(), families.end(), e.family) != families.end();
    e.patterns = json_get_or<std::vector<std::string>>(m, "files", {}, where);
    for (const auto& req : m.value("requires", Json::array()))
      e.requires_repos.push_back({json_get<std::string>(req, "repo", where + ".requires"),
                                  json_get_or<std::vector<std::string>>(req, "files", {}, where + ".requires")});
    r.entries_.push_back(std::move(e));
  }
  return r;
}

const RegistryEntry& Registry::get(const std::string& id) const {
  for (const auto& e : entries_)
    if (e.id == id) return e;
  std::string known;
  for (const auto& e : entries_) known += (known.empty() ? "" : ", ") + e.id;
  throw Error(ErrorCode::invalid_argument, "model '" + id + "' is not in the registry " + path_ + " (known: " + known + ")");
}

std::optional<std::string> local_checkpoint(const RegistryEntry& entry) {
  if (!entry.bundled_dir.empty())
    return fs::is_directory(entry.bundled_dir) ? std::optional<std::string>(entry.bundled_dir) : std::nullopt;
  return hub::HubClient::from_env().cached_snapshot(entry.hf_repo);
}

Json deployment_targets() {
  const std::string path = data_file("targets.json");
  return json_get<Json>(read_json_file(path), "targets", path);
}

Json deployment_target(const std::string& id) {
  for (const auto& t : deployment_targets())
    if (t.value("id", "") == id) return t;
  throw Error(ErrorCode::invalid_argument, "--target " + id + ": unknown (see tether inspect targets)");
}

int64_t meminfo_bytes(const std::string& key) {
  std::ifstream in("/proc/meminfo");
  std::string name, unit;
  int64_t value = 0;
  while (in >> name >> value >> unit)
    if (name == key + ":") return value * 1024;
  return -1;
}

double memory_needed_bytes(int64_t parameters, const std::string& precision) {
  const double bytes_per = precision == "fp32" ? 4.0 : 2.0;
  return double(parameters) * bytes_per * 1.25;  // weights plus activations, caches and the runtime
}

}  // namespace tether::cli
