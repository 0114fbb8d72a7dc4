// Loading and checking models/registry.json (entries, published figures) and finding an entry's checkpoint on this
// machine.
#include "cli/registry.h"

#include <algorithm>
#include <cstdio>
#include <cstdlib>
#include <filesystem>

#include "cli/commands.h"

#include "hub/hub_client.h"
#include "models/family.h"

namespace tether::cli {

namespace fs = std::filesystem;

namespace {

std::string nonempty_string(const Json& j, const std::string& key, const std::string& where) {
  std::string v = json_get<std::string>(j, key, where);
  if (v.empty()) throw Error(ErrorCode::format, where + ": field '" + key + "' is empty");
  return v;
}

// `figures`: each published figure with its source, checked so that `models list|info` never show half a citation.
std::vector<PublishedFigure> parse_figures(const Json& m, const std::string& where) {
  std::vector<PublishedFigure> out;
  if (!m.contains("figures")) return out;
  const Json& list = m["figures"];
  if (!list.is_array()) throw Error(ErrorCode::format, where + ".figures: must be a list");
  for (std::size_t i = 0; i < list.size(); ++i) {
    const std::string at = where + ".figures[" + std::to_string(i) + "]";
    const Json& f = list[i];
    if (!f.is_object()) throw Error(ErrorCode::format, at + ": must be an object");
    PublishedFigure pf;
    pf.benchmark = nonempty_string(f, "benchmark", at);
    pf.metric = nonempty_string(f, "metric", at);
    pf.setting = nonempty_string(f, "setting", at);
    if (!f.contains("value") || !f["value"].is_number())
      throw Error(ErrorCode::format, at + ": field 'value' must be a number" +
                                         (f.contains("value") ? " (got " + f["value"].dump() + ")" : ""));
    pf.value = f["value"].get<double>();
    if (pf.metric.find("(%)") != std::string::npos && (pf.value < 0 || pf.value > 100))
      throw Error(ErrorCode::format, at + ": field 'value' " + f["value"].dump() + " is not a percentage");
    const Json source = json_get<Json>(f, "source", at);
    if (!source.is_object()) throw Error(ErrorCode::format, at + ".source: must be an object with 'title' and 'url'");
    pf.source_title = nonempty_string(source, "title", at + ".source");
    pf.source_url = nonempty_string(source, "url", at + ".source");
    if (pf.source_url.rfind("https://", 0) != 0 && pf.source_url.rfind("http://", 0) != 0)
      throw Error(ErrorCode::format, at + ".source: field 'url' is not an http(s) address: " + pf.source_url);
    out.push_back(std::move(pf));
  }
  return out;
}

}  // namespace

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
    e.subfolder = json_get_or<std::string>(m, "subfolder", "", where);
    if (!e.subfolder.empty() && (e.hf_repo.empty() || fs::path(e.subfolder).is_absolute() ||
                                 e.subfolder.find("..") != std::string::npos))
      throw Error(ErrorCode::format, where + ": 'subfolder' must be a relative folder inside 'hf_repo' (got '" +
                                         e.subfolder + "')");
    if (m.contains("parameters") && !m["parameters"].is_null()) e.parameters = json_get<int64_t>(m, "parameters", where);
    e.supported = json_get_or<bool>(m, "supported", false, where) &&
                  std::find(families.begin(), families.end(), e.family) != families.end();
    e.patterns = json_get_or<std::vector<std::string>>(m, "files", {}, where);
    for (const auto& req : m.value("requires", Json::array()))
      e.requires_repos.push_back({json_get<std::string>(req, "repo", where + ".requires"),
                                  json_get_or<std::vector<std::string>>(req, "files", {}, where + ".requires")});
    e.figures = parse_figures(m, where);
    e.figures_note = json_get_or<std::string>(m, "figures_note", "", where);
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
  const auto snapshot = hub::HubClient::from_env().cached_snapshot(entry.hf_repo);
  if (!snapshot || entry.subfolder.empty()) return snapshot;
  // A repo holding several checkpoints may be cached with other folders only.
  const fs::path dir = fs::path(*snapshot) / entry.subfolder;
  return fs::is_directory(dir) ? std::optional<std::string>(dir.string()) : std::nullopt;
}

std::string figure_value(const PublishedFigure& f) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%g", f.value);
  return std::string(buf) + (f.metric.find("(%)") != std::string::npos ? "%" : "");
}

std::string headline_figure(const RegistryEntry& e) {
  if (e.figures.empty()) return "-";
  const PublishedFigure& f = e.figures.front();
  const std::string label = f.benchmark.substr(0, std::min(f.benchmark.find(" ("), f.benchmark.find(" / ")));
  return label + " " + figure_value(f);
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

}  // namespace tether::cli
