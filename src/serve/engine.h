// What the server serves: a model's spec and a batched predict function, plus what /config and /act report about
// it. A Policy is one implementation; tests substitute a fake without touching the HTTP layer.
#pragma once

#include <string>
#include <vector>

#include "runtime/batcher.h"

namespace tether::serve {

struct Engine {
  models::ModelSpec spec;
  runtime::PredictFn predict;       // called from the batcher's single worker thread only
  std::string model_hash;           // "sha256:<hex of model.safetensors>"
  std::vector<std::string> normalization;  // one line per feature, for /config
  std::vector<std::string> load_warnings;
  std::string backend = "cpu", precision = "fp32", gemm;
};

// Loads the checkpoint directory with Policy::load and hashes its weights file.
Engine load_policy_engine(const std::string& checkpoint_dir, const models::LoadOptions& options = {});

}  // namespace tether::serve
