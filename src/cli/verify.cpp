// Measuring how far one policy's action chunks are from another's or from the oracle's fixture outputs (see verify.h).
#include "cli/verify.h"

#include <cmath>
#include <filesystem>
#include <random>

#include "core/json_util.h"
#include "core/safetensors.h"
#include "models/gr00t.h"

namespace tether::cli {

namespace fs = std::filesystem;

namespace {

CaseDiff diff_of(const std::string& name, const std::vector<float>& a, const std::vector<float>& b) {
  CaseDiff d;
  d.name = name;
  d.values = int64_t(std::min(a.size(), b.size()));
  if (a.size() != b.size()) {
    d.max_abs = d.mean_abs = INFINITY;
    return d;
  }
  double sum = 0;
  for (std::size_t i = 0; i < a.size(); ++i) {
    const double e = std::fabs(double(a[i]) - double(b[i]));
    d.max_abs = std::max(d.max_abs, std::isnan(e) ? INFINITY : e);
    sum += e;
  }
  d.mean_abs = a.empty() ? 0 : sum / double(a.size());
  return d;
}

std::vector<float> flat_actions(const policy::Prediction& p) {
  std::vector<float> out;
  for (const auto& item : p.items) out.insert(out.end(), item.actions.begin(), item.actions.end());
  return out;
}

}  // namespace

std::vector<CaseDiff> compare_seeded(policy::Policy& reference, policy::Policy& candidate, int cases) {
  static const char* kInstructions[] = {"pick up the red cube", "put the cup on the plate",
                                        "open the drawer and take out the blue block", "stack 3 blocks"};
  std::vector<CaseDiff> out;
  for (int c = 0; c < cases; ++c) {
    std::mt19937 gen(uint32_t(1000 + c));
    policy::Observation obs = policy::synthetic_observation(reference.spec());
    for (auto& [camera, img] : obs.images) {
      std::uniform_int_distribution<int> pixel(0, 255);
      for (auto& v : img.rgb) v = uint8_t(pixel(gen));
    }
    std::normal_distribution<float> state(0.f, 1.f);
    for (auto& v : obs.state) v = state(gen);
    obs.instruction = kInstructions[c % 4];
    obs.seed = uint64_t(c);
    out.push_back(diff_of("seeded-" + std::to_string(c), flat_actions(reference.predict({obs})),
                          flat_actions(candidate.predict({obs}))));
  }
  return out;
}

namespace {

// A GR00T fixture (tools/oracle/gr00t_oracle.py): one observation run with one embodiment; metadata `instruction`,
// `input_files` (camera -> path under the case) and `embodiment_tag`. Compared only when `candidate` serves that
// embodiment; lerobot's decode step maps LIBERO's gripper, which is applied to Tether's robot units to compare.
std::vector<CaseDiff> compare_with_gr00t_oracle(const fs::path& root, const SafeTensorsFile& oracle,
                                                policy::Policy& candidate) {
  const auto& meta = oracle.metadata();
  const auto& spec = candidate.spec();
  const std::string tag = meta.at("embodiment_tag");
  if (spec.embodiment != tag) return {};
  policy::Observation obs;
  obs.state = oracle.get("input.state").to_f32();
  obs.instruction = meta.at("instruction");
  obs.noise = oracle.get("input.noise").to_f32();
  const Json files = Json::parse(meta.at("input_files"));
  for (auto cam = files.begin(); cam != files.end(); ++cam)
    obs.images[cam.key()] = vision::load_image((root / cam->get<std::string>()).string());
  std::vector<float> got = flat_actions(candidate.predict({obs}));
  if (models::gr00t_applies_libero_transform(tag)) models::libero_gripper_transform(got, models::action_groups(spec));
  return {diff_of("oracle-" + root.filename().string(), oracle.get("out.actions").to_f32(), got)};
}

}  // namespace

std::vector<CaseDiff> compare_with_oracle(const std::string& reference_dir, policy::Policy& candidate) {
  const fs::path root = fs::path(reference_dir).lexically_normal().parent_path();
  if (!fs::exists(root / "oracle.safetensors") || !fs::is_directory(root / "inputs")) return {};
  const SafeTensorsFile oracle = SafeTensorsFile::open((root / "oracle.safetensors").string());
  if (oracle.metadata().count("embodiment_tag")) return compare_with_gr00t_oracle(root, oracle, candidate);
  const Json instructions = Json::parse(oracle.metadata().at("instructions"));
  const Json files = Json::parse(oracle.metadata().at("input_files"));
  const Tensor state = oracle.get("input.state");
  const std::vector<float> states = state.to_f32(), noise = oracle.get("input.noise").to_f32();
  const auto& spec = candidate.spec();
  std::vector<policy::Observation> batch(std::size_t(state.dim(0)));
  for (std::size_t b = 0; b < batch.size(); ++b) {
    batch[b].state.assign(states.begin() + int64_t(b) * state.dim(1), states.begin() + int64_t(b + 1) * state.dim(1));
    batch[b].instruction = instructions.at(b).get<std::string>();
    const int64_t n = spec.noise_rows() * spec.max_action_dim;
    batch[b].noise.assign(noise.begin() + int64_t(b) * n, noise.begin() + int64_t(b + 1) * n);
    // The cameras the run was given (input_files); the oracle's `cameras` also lists the ones it left out.
    for (auto cam = files.begin(); cam != files.end(); ++cam)
      batch[b].images[cam.key()] = vision::load_image((root / "inputs" / cam->at(b).get<std::string>()).string());
  }
  return {diff_of("oracle-" + root.filename().string(), oracle.get("out.actions").to_f32(),
                  flat_actions(candidate.predict(batch)))};
}

}  // namespace tether::cli
