// The public engine API: load a checkpoint directory, predict action chunks in robot units.
#pragma once

#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "models/family.h"
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
  float adaptive_threshold = 0;  // > 0: stop denoising early (see models::DenoiseControl)
  // Real-time chunking: guide the new chunk towards what is still queued from the previous one.
  struct Rtc {
    std::vector<float> prev_actions;  // leftover of the previous chunk, robot units, [n, action_dim], 1 <= n <= chunk
    int inference_delay = 0;          // actions that run while this chunk is computed, in [0, chunk)
    int execution_horizon = 10;       // >= 1; capped to n
    float max_guidance_weight = 10;
    models::RtcSchedule schedule = models::RtcSchedule::linear;
  };
  std::optional<Rtc> rtc;
};

// A stand-in observation for warm-ups and benchmarks: a mid-grey frame for every camera a client sends (not the
// model's synthetic ones) at the model's input size, a zero state, a short instruction.
Observation synthetic_observation(const models::ModelSpec& spec);

struct ActionChunk {
  int64_t chunk_size = 0, action_dim = 0;
  std::vector<float> actions;  // [chunk_size, action_dim], robot units
  std::vector<std::string> warnings;
  int denoise_steps_used = 0;
};

struct Prediction {
  std::vector<ActionChunk> items;
  models::StageTimings timings;
  double normalize_ms = 0, postprocess_ms = 0, total_ms = 0;
  double flops = 0;  // matrix-product flops of the forward pass (whole batch), as the model's blocks count them
};

class Policy {
 public:
  // Loads the checkpoint through the family that recognises it (models/family.h).
  static std::unique_ptr<Policy> load(const std::string& checkpoint_dir, const models::LoadOptions& options = {});

  const models::ModelSpec& spec() const { return model_->spec(); }
  const models::FamilyDescriptor& family() const { return *family_; }
  const models::Model& model() const { return *model_; }
  const std::string& directory() const { return dir_; }
  // The weight files, relative to directory() (one file, or an index and its shards).
  const std::vector<std::string>& weight_files() const { return weight_files_; }
  // Things the user should know about the checkpoint (missing stats, converted legacy stats, ...), one sentence each.
  const std::vector<std::string>& load_warnings() const { return warnings_; }
  const Normalizer& input_normalizer() const { return pre_; }
  const Normalizer& output_normalizer() const { return post_; }

  Prediction predict(const std::vector<Observation>& batch);
  // Named intermediates of the model, plus "out.actions_normalized" before unnormalisation.
  void set_debug_hook(models::DebugHook hook) {
    debug_ = hook;
    model_->set_debug_hook(std::move(hook));
  }

 private:
  std::string dir_;
  const models::FamilyDescriptor* family_ = nullptr;
  std::vector<std::string> weight_files_;
  std::unique_ptr<models::Model> model_;
  Normalizer pre_, post_;
  std::vector<std::string> warnings_;
  models::DebugHook debug_;
};

}  // namespace tether::policy
