// The model registry shipped with Tether (models/registry.json): ids, families, Hugging Face repos, sizes, and
// where each checkpoint is found on this machine. Shared by `tether go` and `tether models`.
#pragma once

#include <optional>
#include <string>
#include <vector>

#include "cli/hardware.h"
#include "core/json_util.h"

namespace tether::cli {

// A benchmark result published for a model, with where it was published.
struct PublishedFigure {
  std::string benchmark;  // "LIBERO (average of 4 suites)", "LIBERO-10 / LIBERO-Long"
  std::string metric;     // "success rate (%)"
  double value = 0;
  std::string setting;    // what was fine-tuned and evaluated
  std::string source_title, source_url;
};

struct RegistryEntry {
  std::string id, family, description, license;
  std::string hf_repo;      // empty for a bundled checkpoint
  std::string subfolder;    // the checkpoint's folder inside hf_repo, for repos that hold several; empty: the root
  std::string bundled_dir;  // absolute; empty for a hub checkpoint
  std::optional<int64_t> parameters;
  bool supported = false;  // the registry says so and this build has the family
  // Other repos whose files the checkpoint needs (the VLM backbone's config and tokenizer), with patterns.
  struct Requirement {
    std::string repo;
    std::vector<std::string> patterns;
  };
  std::vector<Requirement> requires_repos;
  std::vector<std::string> patterns;  // which files of hf_repo to download
  std::vector<PublishedFigure> figures;  // the first is the headline
  std::string figures_note;              // why there are none, or what to keep in mind reading them
};

// The headline figure in a few characters ("LIBERO 87.3%"): the first figure's benchmark without its qualifier, and
// its value; "-" when the entry has none.
std::string headline_figure(const RegistryEntry& entry);
// "87.3%" (or "87.3" for a metric not in percent).
std::string figure_value(const PublishedFigure& figure);

class Registry {
 public:
  // models/registry.json next to the sources, or TETHER_REGISTRY.
  static Registry load();
  const std::string& path() const { return path_; }
  const std::vector<RegistryEntry>& entries() const { return entries_; }
  // The entry for `id`; an invalid_argument error listing the known ids otherwise.
  const RegistryEntry& get(const std::string& id) const;

 private:
  std::string path_;
  std::vector<RegistryEntry> entries_;
};

// The checkpoint directory of an entry on this machine (bundled, or a snapshot in the Hugging Face cache);
// nullopt when it has not been downloaded.
std::optional<std::string> local_checkpoint(const RegistryEntry& entry);

// Downloads the entry's files (and those of the repos it requires) into the Hugging Face cache; returns the
// checkpoint directory. A bundled entry is returned as is.
std::string pull_model(const RegistryEntry& entry, const std::string& revision = "main");

// Writes a deployment directory for checkpoint `src` into `out` (see `tether export`); returns the largest measured
// max |diff| against the fp32 source. `embodiment_file`: an embodiment JSON (preset or custom) travelling with it.
// `embodiment_tag`: for checkpoints trained on several embodiments (GR00T), the one exported; the export holds only
// its statistics and loads without naming it.
double export_checkpoint(const std::string& src, const std::string& out, const std::string& precision,
                         const std::string& target, const std::string& embodiment_file = "",
                         const std::string& embodiment_tag = "", const std::string& backend = "cpu");

// Prints the registry as a table (or JSON): id, family, source, parameters, support, local presence, headline
// published figure, license.
int list_models(const Registry& reg, bool json);

// The deployment profiles of models/targets.json (`tether inspect targets`), and one of them by id (an
// invalid_argument error naming the flag when unknown).
Json deployment_targets();
Json deployment_target(const std::string& id);

}  // namespace tether::cli
