// `tether predict`: one observation in, one action chunk out, with the latency of each stage.
#include <chrono>
#include <cstdio>
#include <iostream>

#include "cli/commands.h"
#include "cli/observation_args.h"
#include "core/json_util.h"
#include "policy/policy.h"

namespace tether::cli {

namespace {

struct PredictArgs {
  std::string checkpoint;
  ObservationArgs observation;
  std::string precision = "fp32";
  std::string backend = "cpu";
  std::string embodiment_tag;
  bool json = false;
};

int run_predict(const PredictArgs& a) {
  const auto t0 = std::chrono::steady_clock::now();
  auto policy = policy::Policy::load(a.checkpoint, load_options(a.precision, a.embodiment_tag, a.backend));
  const double load_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  for (const auto& w : policy->load_warnings()) std::cerr << "warning: " << w << "\n";
  const auto& spec = policy->spec();

  const policy::Observation obs = a.observation.build(*policy);
  const policy::Prediction p = policy->predict({obs});
  const policy::ActionChunk& chunk = p.items.at(0);
  for (const auto& w : chunk.warnings) std::cerr << "warning: " << w << "\n";
  Json latency = {{"load", load_ms}, {"normalize", p.normalize_ms}};
  for (const auto& stage : spec.stages) latency[stage] = p.timings.get(stage);  // the model's stages, in order
  latency["postprocess"] = p.postprocess_ms;
  latency["total"] = p.total_ms;
  if (a.json) {
    Json actions = Json::array();
    for (int64_t r = 0; r < chunk.chunk_size; ++r)
      actions.push_back(std::vector<float>(chunk.actions.begin() + r * chunk.action_dim,
                                           chunk.actions.begin() + (r + 1) * chunk.action_dim));
    const Json out = {{"actions", actions},
                      {"num_actions", chunk.chunk_size},
                      {"action_dim", chunk.action_dim},
                      {"latency_ms", latency},
                      {"model", {{"family", spec.family}, {"weights_dtype", spec.weights_dtype}}},
                      {"inference_mode", inference_mode(spec)},
                      {"warnings", chunk.warnings}};
    std::cout << out.dump() << "\n";
    return kExitOk;
  }
  std::printf("action chunk: %lld x %lld (robot units)\n", (long long)chunk.chunk_size, (long long)chunk.action_dim);
  for (int64_t r = 0; r < chunk.chunk_size; ++r) {
    std::printf("%4lld ", (long long)r);
    for (int64_t c = 0; c < chunk.action_dim; ++c) std::printf(" %10.5f", chunk.actions[r * chunk.action_dim + c]);
    std::printf("\n");
  }
  std::printf("latency (ms):");
  for (auto it = latency.begin(); it != latency.end(); ++it) std::printf(" %s %.2f", it.key().c_str(), it->get<double>());
  std::printf("\n");
  return kExitOk;
}

}  // namespace

Verb add_predict(CLI::App& app) {
  auto args = std::make_shared<PredictArgs>();
  CLI::App* sub = app.add_subcommand("predict", "Run one observation through a checkpoint and print the action chunk");
  sub->add_option("checkpoint", args->checkpoint, "Checkpoint directory")->required();
  args->observation.add_to(sub, /*required=*/true);
  add_precision_flag(sub, args->precision);
  add_backend_flag(sub, args->backend);
  add_embodiment_tag_flag(sub, args->embodiment_tag);
  sub->add_flag("--json", args->json, "Print JSON instead of a table");
  return {sub, [args] { return run_predict(*args); }};
}

}  // namespace tether::cli
