// The interface every model family implements: a spec of what it takes and gives, and a batched predict.
// How a checkpoint is recognised and loaded is the family descriptor's (models/family.h).
#pragma once

#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "backend/backend.h"
#include "backend/cpu/packed_linear.h"
#include "core/json_util.h"
#include "core/tensor.h"
#include "models/blocks/sampler.h"
#include "vision/image.h"

namespace tether::models {

// One observation as the model sees it: state already normalised by the policy layer.
struct ModelInput {
  std::map<std::string, vision::Image> images;  // camera key as the checkpoint names it -> RGB image
  std::vector<float> state;                     // normalised, unpadded (state_dim values)
  std::string instruction;
  std::vector<float> noise;  // [chunk_size, max_action_dim]; empty -> drawn from `seed`
  uint64_t seed = 0;
  DenoiseControl denoise;  // adaptive steps, RTC guidance; default: plain Euler over every step
};

// Milliseconds per stage, named as ModelSpec::stages names them, in that order.
struct StageTimings {
  std::vector<std::pair<std::string, double>> ms;
  void set(const std::string& stage, double value);  // replaces or appends
  double get(const std::string& stage) const;        // 0 when the stage did not run
};

struct ModelOutput {
  int64_t batch = 0, chunk_size = 0, action_dim = 0;
  std::vector<float> actions;                       // [batch, chunk_size, action_dim], normalised
  std::vector<std::vector<std::string>> warnings;  // per item
  std::vector<int> steps_used;                      // per item: denoise steps run (num_steps unless it stopped early)
  StageTimings timings;
  double flops = 0;  // matrix-product flops of this forward pass (2 per multiply-add), as the blocks count them
};

// A named part of the state or action vector, as a family's modality config names it (GR00T: "left_arm", "gripper",
// ...). The groups of one kind, in order, concatenate to the whole vector.
struct ModalityGroup {
  std::string name;
  int64_t dim = 0;
};

struct ModelSpec {
  std::string family;                // the family descriptor's name
  std::vector<std::string> cameras;  // camera keys in model order, as the checkpoint names them
  // Cameras the model fills itself (placeholders its config declares); a client never sends them.
  std::vector<std::string> synthetic_cameras;
  // A camera may also be named by its key without this prefix ("camera1" for "observation.images.camera1").
  std::string camera_prefix;
  std::string missing_camera_rule;  // one sentence: what happens to a camera a request leaves out
  bool every_camera_required = false;  // a request must give every camera but the synthetic ones (GR00T)
  std::vector<std::string> stages;  // the model's timed stages in order (StageTimings names)
  std::string tokenizer;            // tokenizer kind: "byte_level_bpe", "sentencepiece"
  std::string tokenizer_source;     // the file its vocabulary was read from (tokenizer.json or tokenizer.model)
  std::string state_key, action_key;  // the feature keys the normaliser knows them by
  int64_t state_dim = 0, action_dim = 0, chunk_size = 0, num_steps = 0;
  // Rows the sampler draws and denoises when the model predicts more than it returns (GR00T: its action horizon, of
  // which the checkpoint keeps the first chunk_size); 0: chunk_size. The noise a request sends has these rows.
  int64_t sampled_chunk = 0;
  int64_t noise_rows() const { return sampled_chunk > 0 ? sampled_chunk : chunk_size; }
  // The state and action vectors as named groups in concatenation order; their dims add up to state_dim and
  // action_dim. A lerobot checkpoint has one of each (single_groups). Empty on a spec built by hand: read through
  // state_groups() / action_groups(), which give the single groups then.
  std::vector<ModalityGroup> state_groups, action_groups;
  int64_t max_state_dim = 0, max_action_dim = 0;
  int64_t image_height = 0, image_width = 0;  // what the vision tower receives
  std::string weights_dtype;                   // as stored in the checkpoint
  cpu::Precision precision = cpu::Precision::fp32;  // what the linear layers compute in
  std::string backend = "cpu";                      // the backend it runs on (Backend::name(): "cpu", "cuda")
  // The embodiment served, for checkpoints trained on several (GR00T: a tag of embodiment_id.json); empty otherwise.
  std::string embodiment;
  // The checkpoint's own modality config for that embodiment ({video, state, action, language}, as GR00T's
  // processor_config.json holds it), which the GR00T transport reports as Isaac-GR00T's server does; null when the
  // checkpoint has none.
  Json modality_config;
  // How a request's RTC leftover steers the sampler; rtc_ramp_rate: the inpainting ramp (GR00T's config).
  RtcMethod rtc = RtcMethod::guidance;
  float rtc_ramp_rate = 0;
  // Some action groups are predicted relative to the state (GR00T's use_relative_action, lerobot's
  // use_relative_actions). A previous chunk's leftover was made absolute against an older state: where
  // `relative_rtc_reanchored`, it is made relative to the request's state again before it steers the sampler (lerobot's
  // rollout does so for pi0 / pi0.5); else real-time chunking is refused, as lerobot turns it off (GR00T).
  bool relative_actions = false;
  bool relative_rtc_reanchored = false;
  bool rtc_refused_for_relative() const { return relative_actions && !relative_rtc_reanchored; }
};

struct LoadOptions {
  // fp32 is the reference mode; bf16 runs the linear layers with bf16 weights and inputs (float32
  // accumulation, attention and norms in float32), measured against fp32, never assumed equal.
  cpu::Precision precision = cpu::Precision::fp32;
  // Where the model runs; null: backend::make_default_backend() (TETHER_BACKEND, else the CPU).
  std::shared_ptr<backend::Backend> backend;
  // For checkpoints trained on several embodiments (GR00T): the tag served, as the checkpoint names it. Empty: the
  // checkpoint's only one (an error lists the tags when there are several).
  std::string embodiment;
};

// Called with named intermediates ("mid.vision.<camera>", "mid.prefix_k.0", ...) when set: parity failures are
// located by comparing these with the oracle's, not by guessing.
using DebugHook = std::function<void(const std::string& name, const Tensor& value)>;

class Model {
 public:
  virtual ~Model() = default;
  virtual const ModelSpec& spec() const = 0;
  virtual ModelOutput predict(const std::vector<ModelInput>& batch) = 0;
  void set_debug_hook(DebugHook hook) { debug_ = std::move(hook); }

 protected:
  void dump(const std::string& name, const Tensor& t) const {
    if (debug_) debug_(name, t);
  }
  bool dumping() const { return bool(debug_); }
  // Dumps a backend array (downloaded first).
  template <typename T>
  void dump_array(backend::Backend& be, const std::string& name, DType dtype, Shape shape,
                  backend::Ptr<const T> at) const {
    if (!debug_) return;
    std::vector<T> host(std::size_t(shape_numel(shape)));
    be.download(at, int64_t(host.size()), host.data());
    debug_(name, Tensor{dtype, std::move(shape), host.data(), nullptr});
  }
  // Dumps the first and last layer's prefix K/V ("mid.prefix_k.<layer>", "mid.prefix_v.<layer>"), [B, Lp, kv_heads,
  // head_dim] each, from a cache whose rows hold `kv_heads * head_dim` values.
  void dump_prefix_kv(backend::Backend& be, const std::vector<backend::Array<float>>& k,
                      const std::vector<backend::Array<float>>& v, int64_t capacity, int64_t B, int64_t Lp,
                      int64_t kv_heads, int64_t head_dim) const;

  // The frame every flow-matching predict() shares around its own prefix and velocity. begin_predict checks each
  // item's state and noise sizes against spec() and returns the output with its sizes set. sample_actions draws
  // each item's noise (or takes the explicit one), uploads it to `x`, runs Euler under each item's controls (timed as
  // "denoise") and writes the actions cut from max_action_dim to action_dim.
  ModelOutput begin_predict(const std::vector<ModelInput>& batch) const;
  void sample_actions(backend::Backend& be, const std::vector<ModelInput>& batch, backend::Ptr<float> x,
                      backend::Ptr<float> v, const Schedule& schedule, const VelocityFn& velocity,
                      const std::function<void(backend::Ptr<const float> v)>& on_step0_velocity, ModelOutput& out) const;

  DebugHook debug_;
};

// The camera key `name` stands for: the key itself, or the key without spec.camera_prefix; nullopt when the model
// has no such camera.
std::optional<std::string> find_camera(const ModelSpec& spec, const std::string& name);

// One state group and one action group covering the whole vectors, named after the feature keys without
// "observation." ("observation.state" -> "state", "action" -> "action"): what a lerobot checkpoint has.
void set_single_groups(ModelSpec& spec);
// The spec's groups, or its single groups when it lists none.
std::vector<ModalityGroup> state_groups(const ModelSpec& spec);
std::vector<ModalityGroup> action_groups(const ModelSpec& spec);
// The action groups of what a server answers with `action_dim` values per step: the spec's, a single group taking
// that width (an embodiment mapping may cut a padded output to its joints).
std::vector<ModalityGroup> answered_action_groups(const ModelSpec& spec, int64_t action_dim);
// Groups as JSON, [{name, dim}] in concatenation order (what /config and the GR00T transport report).
Json groups_json(const std::vector<ModalityGroup>& groups);

// Standard-normal noise from a seed: the same seed gives the same noise on every platform (explicit
// Box-Muller over a 64-bit Mersenne Twister, not std::normal_distribution, whose algorithm varies).
void seeded_normal(uint64_t seed, float* out, int64_t n);

}  // namespace tether::models
