// The public engine API: load a checkpoint directory, predict action chunks in robot units.
#pragma once

#include <memory>
#include <string>
#include <vector>

#include "models/model.h"
#include "policy/normalizer.h"

namespace tether::policy {

// One observation in robot units, as a client sends it.
struct Observation {
  std::map<std::string, vision::Image> images;  // camera key (as the checkpoint names it) -> RGB image
  std::vector<float> state;                     // robot units, state_dim values
  std::string instruction;
  std::vector<float> noise;  // optional explicit noise [chunk_size, max_action_dim]; empty -> from `seed`
  uint64_t seed = 0;
};

// A stand-in observation for warm-ups and benchmarks: a mid-grey frame for every real camera at the model's input
// size, a zero state, a short instruction.
Observation synthetic_observation(const models::ModelSpec& spec);

struct ActionChunk {
  int64_t chunk_size = 0, action_dim = 0;
  std::vector<float> actions;  // [chunk_size, action_dim], robot units
  std::vector<std::string> warnings;
};

struct Prediction {
  std::vector<ActionChunk> items;
  models::StageTimings timings;
  double normalize_ms = 0, postprocess_ms = 0, total_ms = 0;
};

class Policy {
 public:
  static std::unique_ptr<Policy> load(const std::string& checkpoint_dir, const models::LoadOptions& options = {});

  const models::ModelSpec& spec() const { return model_->spec(); }
  const std::string& directory() const { return dir_; }
  // Things the user should know about the checkpoint (missing stats, ...), one sentence each.
  const std::vector<std::string>& load_warnings() const { return warnings_; }
  const Normalizer& input_normalizer() const { return pre_; }

  Prediction predict(const std::vector<Observation>& batch);
  // Named intermediates of the model, plus "out.actions_normalized" before unnormalisation.
  void set_debug_hook(models::DebugHook hook) {
    debug_ = hook;
    model_->set_debug_hook(std::move(hook));
  }

 private:
  std::string dir_;
  std::unique_ptr<models::Model> model_;
  Normalizer pre_, post_;
  std::vector<std::string> warnings_;
  models::DebugHook debug_;
};

}  // namespace tether::policy
