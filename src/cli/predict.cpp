// `tether predict`: one observation in, one action chunk out, with the latency of each stage.
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <iostream>
#include <sstream>

#include "cli/commands.h"
#include "core/json_util.h"
#include "core/safetensors.h"
#include "policy/policy.h"

namespace tether::cli {

namespace {

struct PredictArgs {
  std::string checkpoint;
  std::vector<std::string> images;
  std::string state;
  std::string instruction;
  std::string noise_file;
  uint64_t seed = 0;
  bool json = false;
};

std::vector<float> parse_floats(const std::string& text, const std::string& flag) {
  std::vector<float> out;
  std::stringstream ss(text);
  std::string item;
  while (std::getline(ss, item, ',')) {
    try {
      std::size_t used = 0;
      out.push_back(std::stof(item, &used));
      if (used != item.size()) throw std::invalid_argument(item);
    } catch (const std::exception&) {
      throw Error(ErrorCode::invalid_argument, flag + ": '" + item + "' is not a number");
    }
  }
  return out;
}

// Accepts the checkpoint's camera key or its short form ("camera1" for "observation.images.camera1").
std::string resolve_camera(const std::string& name, const std::vector<std::string>& cameras) {
  for (const auto& c : cameras)
    if (c == name || c == "observation.images." + name) return c;
  std::string known;
  for (const auto& c : cameras) known += (known.empty() ? "" : ", ") + c;
  throw Error(ErrorCode::invalid_argument, "--image: the model has no camera '" + name + "' (it has: " + known + ")");
}

int run_predict(const PredictArgs& a) {
  const auto t0 = std::chrono::steady_clock::now();
  auto policy = policy::Policy::load(a.checkpoint);
  const double load_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  for (const auto& w : policy->load_warnings()) std::cerr << "warning: " << w << "\n";
  const auto& spec = policy->spec();

  policy::Observation obs;
  for (const auto& spec_str : a.images) {
    const auto eq = spec_str.find('=');
    if (eq == std::string::npos)
      throw Error(ErrorCode::invalid_argument, "--image expects CAMERA=FILE, got '" + spec_str + "'");
    const std::string camera = resolve_camera(spec_str.substr(0, eq), spec.cameras);
    obs.images[camera] = vision::load_image(spec_str.substr(eq + 1));
  }
  obs.state = parse_floats(a.state, "--state");
  if (int64_t(obs.state.size()) != spec.state_dim)
    throw Error(ErrorCode::invalid_argument, "--state has " + std::to_string(obs.state.size()) +
                                                 " values, the model expects " + std::to_string(spec.state_dim));
  obs.instruction = a.instruction;
  obs.seed = a.seed;
  if (!a.noise_file.empty()) obs.noise = SafeTensorsFile::open(a.noise_file).get("noise").to_f32();

  const policy::Prediction p = policy->predict({obs});
  const policy::ActionChunk& chunk = p.items.at(0);
  for (const auto& w : chunk.warnings) std::cerr << "warning: " << w << "\n";
  const Json latency = {{"load", load_ms},
                        {"normalize", p.normalize_ms},
                        {"preprocess", p.timings.preprocess_ms},
                        {"vision", p.timings.vision_ms},
                        {"prefix", p.timings.prefix_ms},
                        {"denoise", p.timings.denoise_ms},
                        {"postprocess", p.postprocess_ms},
                        {"total", p.total_ms}};
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
                      {"inference_mode", "cpu-fp32"},
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

std::function<int()> add_predict(CLI::App& app) {
  auto args = std::make_shared<PredictArgs>();
  CLI::App* sub = app.add_subcommand("predict", "Run one observation through a checkpoint and print the action chunk");
  sub->add_option("checkpoint", args->checkpoint, "Checkpoint directory (LeRobot layout)")->required();
  sub->add_option("--image", args->images, "CAMERA=FILE (PNG or JPEG), repeatable")->required();
  sub->add_option("--state", args->state, "Robot state, comma-separated (robot units)")->required();
  sub->add_option("--instruction", args->instruction, "Task instruction")->required();
  sub->add_option("--seed", args->seed, "Noise seed (reproducible runs)");
  sub->add_option("--noise", args->noise_file, "safetensors file with a 'noise' tensor [chunk, max_action_dim]");
  sub->add_flag("--json", args->json, "Print JSON instead of a table");
  return [args] { return run_predict(*args); };
}

}  // namespace tether::cli
