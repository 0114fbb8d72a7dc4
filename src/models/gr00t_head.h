// What GR00T N1.7 and N1.6 share after their backbones: the processor_config.json readers and the
// embodiment-conditioned action head with its flow-matching sampler (vlln, optional VL self-attention, the
// alternating DiT, the per-embodiment state / action encoders and decoder). Each family file derives from
// Gr00tModel and adds its backbone (gr00t_n17.cpp: Qwen3-VL; gr00t_n16.cpp: Eagle). docs/design/gr00t.md section 3.
#pragma once

#include <chrono>
#include <filesystem>
#include <functional>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "backend/backend.h"
#include "models/blocks/dit.h"
#include "models/gr00t.h"
#include "models/weights.h"

namespace tether::models {

// processor_config.json's processor_kwargs (the checkpoint's processing settings).
Json gr00t_processor_kwargs(const std::filesystem::path& dir);

// The action head's part of config.json (GR00TN17Config / Gr00tN1d6Config; both name the fields alike).
struct Gr00tHeadConfig {
  int64_t select_layer = 16, backbone_dim = 2048, hidden = 1024, input_dim = 1536, max_state_dim = 132,
          max_action_dim = 132, action_horizon = 40, num_embodiments = 32, max_seq_len = 1024, steps = 4,
          buckets = 1000;
  float rtc_ramp_rate = 6.0f;
  bool add_pos_embed = true, use_vlln = true;
  DitConfig dit;
  int64_t vl_layers = 0, vl_heads = 0, vl_head_dim = 0;
  std::string model_name;

  static Gr00tHeadConfig from_json(const Json& c, const std::string& where, const std::string& default_model_name);
};

// One GR00T checkpoint loaded once, serving any of its embodiments: the backbone, vlln, VL self-attention and DiT
// (about 99% of the bytes) are shared, and each embodiment added has its own category layers (state encoder, action
// encoder and decoder rows), spec and state encoding. predict() runs the selected embodiment; callers sharing one
// model select and predict under mutex() (load_gr00t_embodiment's views do).
class Gr00tModel : public Model {
 public:
  const ModelSpec& spec() const override { return active().spec; }
  // The backbone per observation, then the head for the batch over the sampler's steps, for the selected embodiment.
  ModelOutput predict(const std::vector<ModelInput>& batch) final;

  // Adds the embodiment `tag` of the checkpoint in `dir` (empty: its only one; an unknown tag lists the known ones),
  // its category rows read from `w`, and returns its slot; a tag already added returns its slot.
  std::size_t add_embodiment(const std::filesystem::path& dir, const std::string& tag, Weights& w);
  void select(std::size_t slot) { active_ = slot; }
  const ModelSpec& spec_of(std::size_t slot) const { return embodiments_.at(slot)->spec; }
  std::mutex& mutex() { return mutex_; }

 protected:
  explicit Gr00tModel(const LoadOptions& options);

  // One embodiment's own part: what embodiment_id.json, the modality config and statistics.json say, the spec built
  // from them, and its rows of the category-specific layers.
  struct Embodied {
    Gr00tEmbodiment embodiment;
    ModelSpec spec;
    std::unique_ptr<backend::LinearWeights> state1, state2, act1, act2, act3, dec1, dec2;
  };
  const Embodied& active() const { return *embodiments_.at(active_); }
  std::size_t active_slot() const { return active_; }

  // One observation's backbone output: `len` rows of backbone_dim (before vlln), valid until the next call.
  struct Backbone {
    backend::Ptr<const float> features;
    int64_t len = 0;
    std::vector<uint8_t> image_mask;  // [len]: 1 on image tokens
  };
  virtual Backbone encode_backbone(const ModelInput& in, int64_t item, ModelOutput& out) = 0;
  // The state encoder's input for one observation of the selected embodiment, max_state_dim values zero-padded.
  // Default: the normalised state as the policy passes it (N1.7); N1.6 encodes its raw state itself.
  virtual void head_state(const ModelInput& in, float* out) const;
  // Called by add_embodiment for each new embodiment, in slot order: N1.6 reads its state encoding here.
  virtual void add_state_encoding(const std::filesystem::path& dir, const Gr00tEmbodiment& e) {
    (void)dir;
    (void)e;
  }

  // The prompt's token embeddings into x [len, width], with `rows` (the images' rows in order, row_count of them) in
  // place of the runs of `image_token`; sets b.len and b.image_mask and returns the runs (first token, length).
  // Throws invalid_argument when the runs and the rows differ (an instruction holding image tokens of its own).
  std::vector<std::pair<int64_t, int64_t>> embed_prompt(const backend::Table& embed, const std::vector<int32_t>& ids,
                                                        int32_t image_token, backend::Ptr<const float> rows,
                                                        int64_t row_count, int64_t width, int64_t item,
                                                        backend::Array<int64_t>& ids_buffer, backend::Ptr<float> x,
                                                        Backbone& b);
  // A causal [len, len] mask (nonzero: may attend) in `mask`, grown as needed.
  void upload_causal_mask(int64_t len, backend::Array<uint8_t>& mask);

  // Loads the shared head (after head_ is set), then fills the spec fields every embodiment shares; add_embodiment
  // completes each embodiment's copy.
  void load_head(Weights& w, cpu::Precision precision);
  void fill_spec(const FamilyDescriptor& family, const std::string& tokenizer_source, int64_t image_h, int64_t image_w,
                 cpu::Precision precision, const std::string& weights_dtype, const std::string& where);

  static double elapsed_ms(std::chrono::steady_clock::time_point since) {
    return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - since).count();
  }

  std::shared_ptr<backend::Backend> be_;
  std::unique_ptr<Weights> weights_;  // kept for the model's life: constants view its mapping
  Gr00tHeadConfig head_;

 private:
  struct Prefix {  // one observation's conditioning: vl_embeds [len, backbone_dim]
    int64_t len = 0;
    backend::Array<float> vl;
    std::vector<uint8_t> image_mask;
  };
  void velocity(int64_t B, backend::Ptr<const float> x, float time, backend::Ptr<float> v);

  ModelSpec shared_spec_;  // fill_spec's fields; each embodiment's spec starts from it
  std::string where_;      // config.json, for errors about an embodiment added later
  std::vector<std::unique_ptr<Embodied>> embodiments_;
  std::size_t active_ = 0;
  std::mutex mutex_;

  backend::Array<float> vlln_w_, vlln_b_;
  SelfAttentionStack vl_attention_;
  DiTStack dit_;
  backend::Array<float> action_pos_;  // [action_horizon, input_dim]

  // Per-request buffers, grown once per shape.
  backend::Array<float> context_, state_, state_mid_, state_tok_;
  backend::Array<uint8_t> text_keys_, image_keys_, all_keys_;
  backend::Array<float> noise_x_, noise_v_, act_in_, act_mid_, tokens_, dit_out_, dec_mid_, dec_out_, temb_;
  std::vector<CrossKv> kv_;
  std::vector<backend::Ptr<const uint8_t>> dit_masks_;  // per DiT block: this request's key mask (cross blocks)
  std::vector<float> host_sinusoid_;                     // the action encoder's time row, reused by every step
};

// Loads one embodiment of a GR00T checkpoint as a Model of its own. The checkpoint's shared part is loaded once per
// process for a directory, precision and backend (`make` builds it, with the embodiment options name, from `store`)
// and kept while any embodiment's Model lives; another embodiment of it only adds its category rows, read from
// `store`. Each Model selects its embodiment and predicts under the shared model's mutex.
std::unique_ptr<Model> load_gr00t_embodiment(const std::filesystem::path& dir, const Json& config, TensorStore store,
                                             const LoadOptions& options,
                                             const std::function<std::unique_ptr<Gr00tModel>(TensorStore)>& make);

// Grows `a` to at least n values (activations are sized once per shape).
void grow(backend::Backend& be, backend::Array<float>& a, int64_t n);

}  // namespace tether::models
