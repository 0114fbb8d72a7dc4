// What the server serves: a model's spec and a batched predict function, plus what /config and /act report about
// it. A Policy is one implementation; tests substitute a fake without touching the HTTP layer.
#pragma once

#include <functional>
#include <string>
#include <vector>

#include "runtime/batcher.h"

namespace tether::serve {

struct Engine {
  models::ModelSpec spec;
  runtime::PredictFn predict;       // called from the batcher's single worker thread only
  std::string model_hash;           // models::weights_hash: "sha256:<hex>" of the weights file (or of the shards)
  std::vector<std::string> normalization;  // one line per feature, for /config
  std::vector<std::string> load_warnings;
  std::string model_name;  // the checkpoint directory's name, for traces
  // The state as the model sees it (the similarity skip measures changes in these units); null: identity.
  std::function<std::vector<float>(const std::vector<float>&)> normalize_state;
  // True when the checkpoint has no action stats: its output is in the model's normalised range, not robot units.
  bool actions_normalized = false;
  std::string backend = "cpu", precision = "fp32", gemm;
  std::string compute = "fp32";  // cpu::compute_mode: what the linear layers really ran in
};

// The name a checkpoint directory is known by: its last path component ("models/demo/smolvla-demo/" -> "smolvla-demo").
std::string checkpoint_name(const std::string& checkpoint_dir);

// Loads the checkpoint directory with Policy::load and hashes its weights (models::weights_hash).
Engine load_policy_engine(const std::string& checkpoint_dir, const models::LoadOptions& options = {});

}  // namespace tether::serve
