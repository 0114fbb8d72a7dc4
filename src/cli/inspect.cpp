// `tether inspect`: deployment targets (`inspect targets`) and what a checkpoint contains (`inspect model`).
#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <iostream>

#include "cli/commands.h"
#include "cli/observation_args.h"
#include "cli/registry.h"
#include "core/json_util.h"
#include "policy/policy.h"

namespace tether::cli {

namespace fs = std::filesystem;

std::string data_file(const std::string& name) {
  if (const char* dir = std::getenv("TETHER_DATA_DIR")) return (fs::path(dir) / name).string();
  return (fs::path(TETHER_SOURCE_DIR) / "models" / name).string();
}

namespace {

// The state's and the action's normalisation, one line per feature (what /config reports too).
std::vector<std::string> normalization_lines(const policy::Policy& p) {
  std::vector<std::string> lines = p.input_normalizer().describe();
  for (const auto& line : p.output_normalizer().describe())  // lerobot's pre-processor may list the action too
    if (std::find(lines.begin(), lines.end(), line) == lines.end()) lines.push_back(line);
  return lines;
}

struct InspectArgs {
  std::string model;
  std::string embodiment_tag;
  bool json = false;
};

int run_targets(const InspectArgs& a) {
  const Json targets = deployment_targets();
  if (a.json) {
    std::cout << targets.dump(2) << "\n";
    return kExitOk;
  }
  std::printf("%-10s %-52s %8s  %-6s %-6s %s\n", "target", "name", "memory", "accel", "cc", "default precision");
  for (const auto& t : targets)
    std::printf("%-10s %-52s %6d GB  %-6s %-6s %s\n", t.value("id", "").c_str(), t.value("name", "").c_str(),
                t.value("memory_gb", 0), t.value("accelerator", "").c_str(), t.value("compute_capability", "-").c_str(),
                t.value("default_precision", "").c_str());
  return kExitOk;
}

int run_model(const InspectArgs& a) {
  auto policy = policy::Policy::load(a.model, load_options("fp32", a.embodiment_tag));
  const auto& s = policy->spec();
  const models::TensorStore f = policy->family().open_weights(a.model);
  int64_t params = 0;
  std::map<std::string, int64_t> by_dtype;
  for (const auto& name : f.names()) {
    const auto& e = f.entry(name);
    params += shape_numel(e.shape);
    by_dtype[std::string(dtype_name(e.dtype))] += shape_numel(e.shape);
  }
  const Json out = {{"directory", a.model},
                    {"family", s.family},
                    {"cameras", s.cameras},
                    {"image_size", {s.image_height, s.image_width}},
                    {"state_dim", s.state_dim},
                    {"action_dim", s.action_dim},
                    {"chunk_size", s.chunk_size},
                    {"num_steps", s.num_steps},
                    {"weights_dtype", s.weights_dtype},
                    {"weight_files", policy->weight_files()},
                    {"tokenizer", s.tokenizer},
                    {"tokenizer_source", s.tokenizer_source},
                    {"stages", s.stages},
                    {"parameters", params},
                    {"parameters_by_dtype", by_dtype},
                    {"tensors", f.names().size()},
                    {"normalization", normalization_lines(*policy)},
                    {"warnings", policy->load_warnings()}};
  if (a.json) {
    std::cout << out.dump(2) << "\n";
    return kExitOk;
  }
  for (auto it = out.begin(); it != out.end(); ++it) std::printf("%-20s %s\n", it.key().c_str(), it->dump().c_str());
  return kExitOk;
}

}  // namespace

Verb add_inspect(CLI::App& app) {
  auto args = std::make_shared<InspectArgs>();
  CLI::App* sub = app.add_subcommand("inspect", "Show deployment targets or what a checkpoint contains");
  sub->require_subcommand(1);
  CLI::App* targets = sub->add_subcommand("targets", "Deployment profiles: memory and default precision");
  targets->add_flag("--json", args->json, "Print JSON");
  CLI::App* model = sub->add_subcommand("model", "Family, cameras, dimensions, parameters and normalisation of a checkpoint");
  model->add_option("checkpoint", args->model, "Checkpoint directory")->required();
  add_embodiment_tag_flag(model, args->embodiment_tag);
  model->add_flag("--json", args->json, "Print JSON");
  return {sub, [args, targets] { return targets->parsed() ? run_targets(*args) : run_model(*args); }};
}

}  // namespace tether::cli
