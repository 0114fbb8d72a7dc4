// The observation flags shared by predict, bench and verify (--image, --state, --instruction, --seed, --noise).
#include "cli/observation_args.h"

#include <sstream>

#include "backend/backend.h"
#include "core/safetensors.h"

namespace tether::cli {

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

void add_precision_flag(CLI::App* sub, std::string& value) {
  sub->add_option("--precision", value,
                  "fp32 (reference), bf16 or fp16 (half-size weights; bf16 GEMM where the CPU has bf16 instructions, "
                  "otherwise weights widened to fp32 in the kernel)")
      ->check(CLI::IsMember({"fp32", "bf16", "fp16"}))
      ->capture_default_str();
}

void add_embodiment_tag_flag(CLI::App* sub, std::string& value) {
  sub->add_option("--embodiment-tag", value,
                  "Embodiment served, for checkpoints trained on several (GR00T: a tag of its embodiment_id.json); "
                  "default: the checkpoint's only one");
}

void add_backend_flag(CLI::App* sub, std::string& value) {
  sub->add_option("--backend", value,
                  "Where the model runs: cpu, cuda (an NVIDIA GPU; fails with exit code 2 where there is none) or "
                  "auto (cuda when this build has it and a GPU is usable, else cpu)")
      ->check(CLI::IsMember({"cpu", "cuda", "auto"}))
      ->capture_default_str();
}

models::LoadOptions load_options(const std::string& precision, const std::string& embodiment_tag,
                                 const std::string& backend) {
  models::LoadOptions o;
  o.precision = cpu::parse_precision(precision);
  o.embodiment = embodiment_tag;
  // Checked before the model loads, so a missing GPU costs one line, not a load.
  if (std::string why; !backend::backend_usable(backend, &why)) throw Error(ErrorCode::invalid_argument, why);
  o.backend = backend::make_backend(backend);
  return o;
}

std::string inference_mode(const models::ModelSpec& spec) {
  if (spec.backend != "cpu") return spec.backend + "-" + cpu::precision_name(spec.precision);
  return std::string("cpu-") + cpu::compute_mode(spec.precision);
}

namespace {

// Accepts the checkpoint's camera key or its short form (the key without the spec's camera prefix).
std::string resolve_camera(const std::string& name, const models::ModelSpec& spec) {
  if (auto c = models::find_camera(spec, name)) return *c;
  std::string known;
  for (const auto& c : spec.cameras) known += (known.empty() ? "" : ", ") + c;
  throw Error(ErrorCode::invalid_argument, "--image: the model has no camera '" + name + "' (it has: " + known + ")");
}

}  // namespace

void ObservationArgs::add_to(CLI::App* sub, bool required) {
  auto* image = sub->add_option("--image", images, "CAMERA=FILE (PNG or JPEG), repeatable; CAMERA as the checkpoint names it, or its short form");
  auto* st = sub->add_option("--state", state, "Robot state, comma-separated, robot units (use --state=-1,2 for a leading minus)");
  auto* instr = sub->add_option("--instruction", instruction, "Task instruction");
  if (required) {
    image->required();
    st->required();
    instr->required();
  }
  sub->add_option("--seed", seed, "Noise seed (reproducible runs)");
  sub->add_option("--noise", noise_file, "safetensors file with a 'noise' tensor [chunk, max_action_dim]");
}

policy::Observation ObservationArgs::build(const policy::Policy& policy) const {
  const auto& spec = policy.spec();
  policy::Observation obs;
  for (const auto& spec_str : images) {
    const auto eq = spec_str.find('=');
    if (eq == std::string::npos)
      throw Error(ErrorCode::invalid_argument, "--image expects CAMERA=FILE, got '" + spec_str + "'");
    obs.images[resolve_camera(spec_str.substr(0, eq), spec)] = vision::load_image(spec_str.substr(eq + 1));
  }
  if (images.empty()) obs.images = policy::synthetic_observation(spec).images;
  obs.state = state.empty() ? std::vector<float>(std::size_t(spec.state_dim), 0.f) : parse_floats(state, "--state");
  if (int64_t(obs.state.size()) != spec.state_dim)
    throw Error(ErrorCode::invalid_argument, "--state has " + std::to_string(obs.state.size()) +
                                                 " values, the model expects " + std::to_string(spec.state_dim));
  obs.instruction = instruction;
  obs.seed = seed;
  if (!noise_file.empty()) {
    obs.noise = SafeTensorsFile::open(noise_file).get("noise").to_f32();
    if (int64_t(obs.noise.size()) != spec.noise_rows() * spec.max_action_dim)
      throw Error(ErrorCode::invalid_argument, noise_file + ": 'noise' has " + std::to_string(obs.noise.size()) +
                                                   " values, expected " + std::to_string(spec.noise_rows()) + " x max_action_dim = " +
                                                   std::to_string(spec.noise_rows() * spec.max_action_dim));
  }
  return obs;
}

}  // namespace tether::cli
