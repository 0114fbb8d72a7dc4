// pi0 and pi0.5 (lerobot's ports of openpi) as wiring of the shared blocks: PaliGemma's SigLIP tower and projector,
// the Gemma prefix decoder whose K/V are computed once per request, a Gemma action expert attending jointly to them,
// and the Euler sampler. pi0 feeds the state as a suffix token and the time through the action-time MLP; pi0.5 writes
// the discretised state into the prompt and conditions the expert's adaptive RMSNorms on the time.
#include "models/pi0.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <map>
#include <optional>

#include "backend/backend.h"
#include "models/backbone.h"
#include "models/blocks/action_expert.h"
#include "models/blocks/attention_masks.h"
#include "models/blocks/decoder.h"
#include "models/blocks/kept_per_time.h"
#include "models/blocks/linear.h"
#include "models/blocks/sampler.h"
#include "models/blocks/vision_tower.h"
#include "models/lerobot/checkpoint.h"
#include "text/tokenizer.h"
#include "vision/preprocess.h"

namespace tether::models {

namespace fs = std::filesystem;
using backend::Ptr;

namespace {

constexpr const char* kDefaultTokenizer = "google/paligemma-3b-pt-224";
// SigLIP so400m's attention heads are 72 wide (1152 / 16); the checkpoint's config does not say how many there are.
constexpr int64_t kSiglipHeadDim = 72;
const std::string kVlm = "model.paligemma_with_expert.paligemma.model.";
const std::string kExpert = "model.paligemma_with_expert.gemma_expert.model.";

double ms_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
}

// openpi's Gemma variants (gemma.py get_config): only the head counts are read from here; widths, depths and head
// sizes come from the tensors, so a checkpoint of another size loads as long as its head counts are the variant's.
struct HeadCounts {
  int64_t heads = 0, kv_heads = 0;
};
HeadCounts variant_heads(const std::string& variant, const std::string& where) {
  if (variant == "gemma_300m" || variant == "gemma_2b") return {8, 1};
  throw Error(ErrorCode::unsupported, where + ": Gemma variant '" + variant + "' (known: gemma_300m, gemma_2b)");
}

// The key renames lerobot's from_pretrained applies (_fix_pytorch_state_dict_keys, then the "model." prefix), and
// lm_head standing in for PaliGemma's tied embed_tokens when a checkpoint stores only one of them.
void normalise_keys(TensorStore& w, bool pi05) {
  for (const std::string& name : w.names()) {
    if (name.rfind("model.", 0) == 0) continue;
    std::string to = name;
    const std::string pi0_name = "action_time_mlp_", pi05_name = "time_mlp_";
    if (!pi05 && name.rfind(pi05_name, 0) == 0) to = pi0_name + name.substr(pi05_name.size());
    if (pi05 && name.rfind(pi0_name, 0) == 0) to = pi05_name + name.substr(pi0_name.size());
    if (pi05 && name.rfind("state_proj.", 0) == 0) {
      w.hide(name);  // pi0.5 has no state projection; upstream skips the key
      continue;
    }
    w.rename(name, "model." + to);
  }
  const std::string embed = kVlm + "language_model.embed_tokens.weight";
  if (!w.contains(embed)) w.rename("model.paligemma_with_expert.paligemma.lm_head.weight", embed);
}

int64_t count_layers(const TensorStore& w, const std::string& prefix) {
  int64_t n = 0;
  for (const std::string& name : w.names()) {
    if (name.rfind(prefix, 0) != 0) continue;
    const std::size_t dot = name.find('.', prefix.size());
    if (dot == std::string::npos) continue;
    try {
      n = std::max<int64_t>(n, std::stoll(name.substr(prefix.size(), dot - prefix.size())) + 1);
    } catch (const std::exception&) {
    }
  }
  return n;
}

const Shape& shape_of(const TensorStore& w, const std::string& name) { return w.entry(name).shape; }

// A Gemma decoder's sizes from its tensors (widths, depth, head size) and its variant (head counts).
DecoderConfig gemma_config(const TensorStore& w, const std::string& prefix, const std::string& variant, bool adaptive,
                           const std::string& where, const std::optional<std::array<int64_t, 2>>& heads = std::nullopt) {
  const HeadCounts hc = heads ? HeadCounts{(*heads)[0], (*heads)[1]} : variant_heads(variant, where);
  DecoderConfig c;
  c.layers = count_layers(w, prefix + "layers.");
  if (c.layers == 0) throw Error(ErrorCode::format, w.label() + ": no tensors under " + prefix + "layers.");
  const std::string l0 = prefix + "layers.0.";
  c.heads = hc.heads;
  c.kv_heads = hc.kv_heads;
  const Shape& k = shape_of(w, l0 + "self_attn.k_proj.weight");
  const Shape& q = shape_of(w, l0 + "self_attn.q_proj.weight");
  const Shape& gate = shape_of(w, l0 + "mlp.gate_proj.weight");
  if (k.size() != 2 || q.size() != 2 || gate.size() != 2 || c.kv_heads <= 0 || k[0] % c.kv_heads != 0)
    throw Error(ErrorCode::format, w.label() + ": " + l0 + "self_attn projections are not [out, in] matrices");
  c.hidden = q[1];
  c.head_dim = k[0] / c.kv_heads;
  c.intermediate = gate[0];
  if (q[0] != c.heads * c.head_dim)
    throw Error(ErrorCode::format, w.label() + ": " + l0 + "self_attn.q_proj.weight has " + std::to_string(q[0]) +
                                       " rows; " + (heads ? std::string("the config") : "variant " + variant) +
                                       " has " + std::to_string(c.heads) +
                                       " heads of " + std::to_string(c.head_dim) + " (from k_proj)");
  c.rms_norm_eps = 1e-6f;  // GemmaConfig's default, which lerobot keeps
  c.norm = adaptive ? NormKind::adaptive_rms : NormKind::rms_one_plus;
  c.mlp = MlpKind::geglu_tanh;
  c.rope_wavelength = 10000.0f;  // GemmaConfig's rope_theta
  c.rope_angles = backend::RopeAngles::inverse_frequency;  // transformers' GemmaRotaryEmbedding
  if (adaptive) c.cond_dim = c.hidden;  // adarms_cond_dim = the expert's width
  return c;
}

// PaliGemma's SigLIP tower from its tensors: patch and width from the patch embedding, depth by counting layers.
VisionConfig siglip_config(const TensorStore& w, const std::string& prefix, int64_t image_size,
                           std::optional<int64_t> heads = std::nullopt) {
  VisionConfig c;
  const Shape& patch = shape_of(w, prefix + "embeddings.patch_embedding.weight");
  if (patch.size() != 4) throw Error(ErrorCode::format, w.label() + ": " + prefix + "embeddings.patch_embedding.weight is not 4-d");
  c.hidden = patch[0];
  c.channels = patch[1];
  c.patch = patch[2];
  c.layers = count_layers(w, prefix + "encoder.layers.");
  c.intermediate = shape_of(w, prefix + "encoder.layers.0.mlp.fc1.weight").at(0);
  if (heads) {
    if (*heads <= 0 || c.hidden % *heads != 0)
      throw Error(ErrorCode::format, w.label() + ": SigLIP width " + std::to_string(c.hidden) + " does not split into " +
                                         std::to_string(*heads) + " heads");
    c.heads = *heads;
  } else {
    if (c.hidden % kSiglipHeadDim != 0)
      throw Error(ErrorCode::unsupported, w.label() + ": SigLIP width " + std::to_string(c.hidden) +
                                              " is not a whole number of 72-wide heads (so400m's)");
    c.heads = c.hidden / kSiglipHeadDim;
  }
  c.image_size = image_size;
  c.layer_norm_eps = 1e-6f;
  c.position_ids = VisionConfig::PositionIds::sequential;
  c.post_norm = true;
  const int64_t side = image_size / c.patch;
  const Shape& pos = shape_of(w, prefix + "embeddings.position_embedding.weight");
  if (image_size % c.patch != 0 || pos.empty() || pos[0] != side * side)
    throw Error(ErrorCode::format, w.label() + ": image_resolution " + std::to_string(image_size) + " with patch " +
                                       std::to_string(c.patch) + " needs " + std::to_string(side * side) +
                                       " position embeddings, the checkpoint has " +
                                       (pos.empty() ? std::string("none") : std::to_string(pos[0])));
  return c;
}

struct TokenizerSettings {
  std::string name = kDefaultTokenizer;
  int max_length = 48;
  bool pad_right = true, truncation = true, max_length_padding = true;
};

// The tokenizer step of policy_preprocessor.json (tokenizer repo, max length, padding), else the config's defaults.
TokenizerSettings read_tokenizer_settings(const fs::path& dir, const Json& config, int default_max_length) {
  TokenizerSettings s;
  const std::string where = (dir / "config.json").string();
  s.max_length = json_get_or<int>(config, "tokenizer_max_length", default_max_length, where);
  const fs::path pre = dir / "policy_preprocessor.json";
  if (!fs::exists(pre)) return s;
  const Json p = read_json_file(pre.string());
  for (const auto& step : p.value("steps", Json::array())) {
    if (step.value("registry_name", "") != "tokenizer_processor") continue;
    const Json& c = step.value("config", Json::object());
    s.name = json_get_or<std::string>(c, "tokenizer_name", s.name, pre.string());
    s.max_length = json_get_or<int>(c, "max_length", s.max_length, pre.string());
    s.truncation = json_get_or<bool>(c, "truncation", true, pre.string());
    s.pad_right = json_get_or<std::string>(c, "padding_side", "right", pre.string()) == "right";
    s.max_length_padding = json_get_or<std::string>(c, "padding", "max_length", pre.string()) == "max_length";
  }
  return s;
}

// Python's str.isspace() for one code point (what str.strip() removes).
bool python_space(char32_t c) {
  return (c >= 0x09 && c <= 0x0d) || (c >= 0x1c && c <= 0x20) || c == 0x85 || c == 0xa0 || c == 0x1680 ||
         (c >= 0x2000 && c <= 0x200a) || c == 0x2028 || c == 0x2029 || c == 0x202f || c == 0x205f || c == 0x3000;
}

// Decodes the UTF-8 code point at s[i] (length in *len); invalid bytes count as one non-space unit of length 1 (the
// tokenizer rejects the text later with its own message).
char32_t code_point_at(const std::string& s, std::size_t i, std::size_t* len) {
  const auto u = static_cast<unsigned char>(s[i]);
  int n = u < 0x80 ? 1 : (u >> 5) == 0x6 ? 2 : (u >> 4) == 0xe ? 3 : (u >> 3) == 0x1e ? 4 : 0;
  if (n == 0 || i + std::size_t(n) > s.size()) {
    *len = 1;
    return 0xfffd;
  }
  char32_t c = n == 1 ? u : u & (0xff >> (n + 1));
  for (int k = 1; k < n; ++k) c = (c << 6) | (static_cast<unsigned char>(s[i + k]) & 0x3f);
  *len = std::size_t(n);
  return c;
}

std::string python_strip(const std::string& s) {
  std::vector<std::pair<std::size_t, std::size_t>> cps;  // (offset, length) of each code point
  for (std::size_t i = 0, len = 0; i < s.size(); i += len) {
    code_point_at(s, i, &len);
    cps.push_back({i, len});
  }
  std::size_t a = 0, b = cps.size(), len = 0;
  while (a < b && python_space(code_point_at(s, cps[a].first, &len))) ++a;
  while (b > a && python_space(code_point_at(s, cps[b - 1].first, &len))) --b;
  if (a == b) return "";
  return s.substr(cps[a].first, cps[b - 1].first + cps[b - 1].second - cps[a].first);
}

// np.digitize(x, np.linspace(-1, 1, 257)[:-1]) - 1: the number of bin edges -1 + k / 128 (k < 256, exact in
// float64) at or below x, minus one; -1 below the first edge, 255 from the last one up.
int state_bin(float x) {
  int count = 0;
  for (int k = 0; k < 256; ++k)
    if (-1.0 + double(k) * (2.0 / 256.0) <= double(x)) ++count;
  return count - 1;
}

class PiZero final : public Model {
 public:
  PiZero(const fs::path& dir, const Json& config, TensorStore weights, const LoadOptions& options, bool pi05,
         const PiZeroOptions& pizero);
  const ModelSpec& spec() const override { return spec_; }
  ModelOutput predict(const std::vector<ModelInput>& batch) override;

 private:
  std::string prompt(const ModelInput& item) const;
  text::BatchEncoding encode_prompts(const std::vector<ModelInput>& batch, ModelOutput& out) const;
  void prepare_image(const vision::Image& img, int64_t camera, float* out, std::vector<std::string>& warnings) const;
  void build_prefix(const std::vector<ModelInput>& batch, ModelOutput& out);
  void run_prefix();
  void denoise_step(Ptr<const float> x, float time, Ptr<float> v);
  void time_sinusoid(float time);     // into time_emb_
  void adarms_condition(float time);  // pi0.5: into cond_
  // pi0.5: what the time alone decides, for every item of every request: the expert's adaptive modulations
  // (ActionExpert::adaptive_modulations), then the final norm's [scale | shift | gate]; kept per time (37
  // matrix-vector products per step at full size).
  Ptr<const float> time_modulations(float time);
  void ensure_buffers(int64_t batch, int64_t prefix_len);
  double flops(int64_t images, int64_t steps_run) const;

  bool pi05_ = false;
  PiZeroOptions pz_;
  ModelSpec spec_;
  TokenizerSettings tok_settings_;
  std::optional<text::PretrainedTokenizer> tokenizer_;
  double min_period_ = 4e-3, max_period_ = 4.0;

  std::shared_ptr<backend::Backend> be_;
  std::unique_ptr<Weights> weights_;
  DecoderConfig text_cfg_, expert_cfg_;
  VisionTower vision_;
  std::unique_ptr<backend::LinearWeights> projector_;
  std::unique_ptr<backend::Table> embed_tokens_;
  DecoderStack vlm_;
  ActionExpert expert_;
  backend::Array<float> expert_norm_;                       // pi0: the final norm's weight
  std::unique_ptr<backend::LinearWeights> expert_norm_mod_;  // pi0.5: the final adaptive norm's dense
  std::unique_ptr<backend::LinearWeights> state_proj_, action_in_, action_out_, time_in_, time_out_;

  // Per-request state, sized once per (batch, prefix length).
  int64_t B_ = 0, Lp_ = 0, suffix_base_ = 0;  // suffix_base_: cache rows before the action tokens (prefix + state)
  std::vector<float> host_pixels_, host_state_;
  std::vector<uint8_t> prefix_pad_, host_mask_, host_state_mask_, host_action_mask_;
  std::vector<int8_t> prefix_att_;
  std::vector<int64_t> host_pos_, host_state_pos_, host_action_pos_;
  backend::Array<float> pixels_, vision_out_, img_tokens_, prefix_x_, state_, state_x_;
  backend::Array<int64_t> token_ids_, prefix_pos_, state_pos_, action_pos_;
  backend::Array<uint8_t> prefix_mask_, state_mask_, action_mask_;
  KvCache cache_;
  backend::Array<float> x_t_, v_t_, suffix_x_, cat_, time_emb_, time_h_, cond_, mlp_h_, normed_;
  KeptPerTime<uint32_t> time_modulations_;  // by the time's float bits
  int64_t images_run_ = 0;
};

PiZero::PiZero(const fs::path& dir, const Json& config, TensorStore store, const LoadOptions& options, bool pi05,
               const PiZeroOptions& pizero)
    : pi05_(pi05), pz_(pizero) {
  const cpu::Precision precision = options.precision;
  spec_.precision = precision;
  be_ = options.backend ? options.backend : backend::make_default_backend();
  spec_.backend = be_->name();
  backend::Backend& be = *be_;
  const std::string where = (dir / "config.json").string();
  const FamilyDescriptor& family = pz_.family ? *pz_.family : pi05 ? pi05_family() : pi0_family();
  spec_.family = family.name;
  spec_.stages = family.stages;
  spec_.missing_camera_rule = family.missing_camera_rule;
  spec_.tokenizer = tokenizer_kind_name(family.tokenizer);
  spec_.camera_prefix = "observation.images.";
  spec_.state_key = "observation.state";
  spec_.action_key = "action";

  spec_.chunk_size = json_get_or<int64_t>(config, "chunk_size", 50, where);
  spec_.num_steps = json_get_or<int64_t>(config, "num_inference_steps", 10, where);
  spec_.max_state_dim = json_get_or<int64_t>(config, "max_state_dim", 32, where);
  spec_.max_action_dim = json_get_or<int64_t>(config, "max_action_dim", 32, where);
  min_period_ = json_get_or<double>(config, "min_period", 4e-3, where);
  max_period_ = json_get_or<double>(config, "max_period", 4.0, where);
  const auto resolution = json_get_or<std::vector<int64_t>>(config, "image_resolution", {224, 224}, where);
  if (resolution.size() != 2 || resolution[0] != resolution[1] || resolution[0] <= 0)
    throw Error(ErrorCode::format, where + ": image_resolution must be a square [size, size] (PaliGemma's)");
  spec_.image_height = spec_.image_width = resolution[0];
  // use_relative_actions: the processor pipelines decide, as lerobot loads them; the policy's post-processing adds the
  // state back (lerobot::read_relative_actions), and an RTC leftover is made relative to the request's state again.
  std::vector<std::string> relative_warnings;  // reported with the normaliser's
  spec_.relative_actions = !lerobot::read_relative_actions(dir.string(), config, relative_warnings).empty();
  spec_.relative_rtc_reanchored = spec_.relative_actions;

  // Features: cameras in input_features order (as upstream iterates image_features), the config's empty cameras
  // after them (validate_features adds them, and a saved config may already list them).
  const Json& inputs = json_get<Json>(config, "input_features", where);
  spec_.state_dim = spec_.max_state_dim;  // validate_features' default state feature
  for (auto it = inputs.begin(); it != inputs.end(); ++it) {
    const std::string type = json_get<std::string>(*it, "type", where + ": input_features." + it.key());
    const auto shape = json_get<std::vector<int64_t>>(*it, "shape", where + ": input_features." + it.key());
    if (type == "VISUAL") spec_.cameras.push_back(it.key());
    if (type == "STATE") {
      spec_.state_key = it.key();
      spec_.state_dim = shape.at(0);
    }
  }
  const int64_t empty_cameras = json_get_or<int64_t>(config, "empty_cameras", 0, where);
  for (int64_t i = 0; i < empty_cameras; ++i) {
    const std::string key = "observation.images.empty_camera_" + std::to_string(i);
    if (std::find(spec_.cameras.begin(), spec_.cameras.end(), key) == spec_.cameras.end()) spec_.cameras.push_back(key);
    spec_.synthetic_cameras.push_back(key);
  }
  spec_.action_dim = spec_.max_action_dim;
  const Json& outputs = json_get<Json>(config, "output_features", where);
  for (auto it = outputs.begin(); it != outputs.end(); ++it)
    if (json_get<std::string>(*it, "type", where) == "ACTION")
      spec_.action_dim = json_get<std::vector<int64_t>>(*it, "shape", where).at(0);
  if (spec_.cameras.size() == spec_.synthetic_cameras.size())
    throw Error(ErrorCode::format, where + ": input_features has no VISUAL feature");
  if (spec_.state_dim > spec_.max_state_dim)
    throw Error(ErrorCode::format, where + ": the state has " + std::to_string(spec_.state_dim) +
                                       " values, more than max_state_dim " + std::to_string(spec_.max_state_dim));
  if (spec_.action_dim > spec_.max_action_dim)
    throw Error(ErrorCode::format, where + ": the action has " + std::to_string(spec_.action_dim) +
                                       " values, more than max_action_dim " + std::to_string(spec_.max_action_dim));
  set_single_groups(spec_);

  if (pz_.prompt == PiZeroOptions::Prompt::lerobot) {
    tok_settings_ = read_tokenizer_settings(dir, config, pi05 ? 200 : 48);
    const fs::path tok_dir = find_backbone_dir(dir, tok_settings_.name, "the tokenizer_processor step's tokenizer_name");
    tokenizer_.emplace(text::load_pretrained_tokenizer(tok_dir.string()));
  } else {
    if (pz_.max_length <= 0) throw Error(ErrorCode::invalid_argument, where + ": the prompt's max_length must be > 0");
    tok_settings_.name = pz_.tokenizer_model.string();
    tok_settings_.max_length = pz_.max_length;
    tokenizer_.emplace(text::load_gemma_sentencepiece(pz_.tokenizer_model.string()));
    if (!tokenizer_->bos_token_id)
      throw Error(ErrorCode::format, pz_.tokenizer_model.string() + ": no <bos> piece (the prompt starts with BOS)");
  }
  spec_.tokenizer_source = tokenizer_->source;
  if (pz_.image_norm == PiZeroOptions::ImageNorm::mean_std_255) {
    const std::size_t n = spec_.cameras.size();
    if (pz_.image_mean.size() != pz_.image_std.size() ||
        (pz_.image_mean.size() != 1 && pz_.image_mean.size() != n))
      throw Error(ErrorCode::invalid_argument, where + ": image mean/std for " + std::to_string(pz_.image_mean.size()) +
                                                   " cameras, the model has " + std::to_string(n));
    for (const auto& s : pz_.image_std)
      for (double v : s)
        if (!(v != 0.0) || !std::isfinite(v)) throw Error(ErrorCode::format, where + ": an image std is 0 or not finite");
  }

  // Weights: upstream's key renames first, then the sizes the tensors imply.
  normalise_keys(store, pi05);
  const std::string vlm_variant = json_get_or<std::string>(config, "paligemma_variant", "gemma_2b", where);
  const std::string expert_variant = json_get_or<std::string>(config, "action_expert_variant", "gemma_300m", where);
  text_cfg_ = gemma_config(store, kVlm + "language_model.", vlm_variant, false, where, pz_.vlm_heads);
  expert_cfg_ = gemma_config(store, kExpert, expert_variant, pi05, where, pz_.expert_heads);
  const VisionConfig vision_cfg =
      siglip_config(store, kVlm + "vision_tower.vision_model.", spec_.image_height, pz_.vision_heads);
  if (expert_cfg_.layers != text_cfg_.layers)
    throw Error(ErrorCode::format, store.label() + ": the action expert has " + std::to_string(expert_cfg_.layers) +
                                       " layers and the VLM " + std::to_string(text_cfg_.layers) +
                                       " (each expert layer reads the same VLM layer's K/V)");
  if (expert_cfg_.head_dim != text_cfg_.head_dim || expert_cfg_.kv_heads != text_cfg_.kv_heads)
    throw Error(ErrorCode::format, store.label() + ": the action expert's K/V heads differ from the VLM's");
  const std::string embed = kVlm + "language_model.embed_tokens.weight";
  const Shape& embed_shape = shape_of(store, embed);
  text_cfg_.vocab = embed_shape.empty() ? 0 : embed_shape[0];
  // transformers >= 5.4 scales inside the embedding (GemmaTextScaledWordEmbedding), once: sqrt(width) as a float32
  // buffer cast to the model's dtype. lerobot builds the model in the config's `dtype`, so with "bfloat16" the
  // buffer is rounded to bf16 (45.25 for 45.2548 at width 2048) and stays so when the policy is later cast to
  // float32; with "float32" it is the float32 root, whatever the file's dtype. Images are not scaled.
  text_cfg_.embedding_scale = float(std::sqrt(double(text_cfg_.hidden)));
  if (pz_.embedding_scale_in_config_dtype && json_get_or<std::string>(config, "dtype", "float32", where) == "bfloat16") {
    text_cfg_.embedding_scale = bf16_to_f32(f32_to_bf16(text_cfg_.embedding_scale));
    // The rotary embeddings' inv_freq buffers are rounded to bf16 the same way.
    text_cfg_.rope_angles = expert_cfg_.rope_angles = backend::RopeAngles::inverse_frequency_bf16;
  }

  weights_ = std::make_unique<Weights>(std::move(store));
  Weights& w = *weights_;
  const int64_t D = text_cfg_.hidden, E = expert_cfg_.hidden, A = spec_.max_action_dim;
  vision_.load(be, w, kVlm + "vision_tower.vision_model.", vision_cfg, precision);
  projector_ = load_linear(be, w, kVlm + "multi_modal_projector.linear", D, vision_cfg.hidden, true, precision);
  embed_tokens_ = be.table(w.raw(embed, {text_cfg_.vocab, D}));
  // The prefix's last layer feeds nothing but its K/V.
  vlm_.load(be, w, kVlm + "language_model.layers.", text_cfg_, text_cfg_.layers, precision, /*last_kv_only=*/true);
  const std::vector<DecoderLayer::Attention> kinds(std::size_t(expert_cfg_.layers), DecoderLayer::Attention::self);
  const int64_t kv_dim = text_cfg_.kv_heads * text_cfg_.head_dim;
  expert_.load(be, w, kExpert + "layers.", expert_cfg_, E, expert_cfg_.intermediate, kinds, kv_dim, precision);
  if (pi05) {
    expert_norm_mod_ = load_linear(be, w, kExpert + "norm.dense", 3 * E, E, true, precision);
    time_in_ = load_linear(be, w, "model.time_mlp_in", E, E, true, precision);
    time_out_ = load_linear(be, w, "model.time_mlp_out", E, E, true, precision);
  } else {
    expert_norm_ = be.constant(w.f32(kExpert + "norm.weight", {E}), E);
    state_proj_ = load_linear(be, w, "model.state_proj", E, spec_.max_state_dim, true, precision);
    time_in_ = load_linear(be, w, "model.action_time_mlp_in", E, 2 * E, true, precision);
    time_out_ = load_linear(be, w, "model.action_time_mlp_out", E, E, true, precision);
  }
  action_in_ = load_linear(be, w, "model.action_in_proj", E, A, true, precision);
  action_out_ = load_linear(be, w, "model.action_out_proj", A, E, true, precision);
  spec_.weights_dtype = w.stored_dtype();
  w.finish_loading();
}

void PiZero::ensure_buffers(int64_t batch, int64_t prefix_len) {
  if (batch == B_ && prefix_len == Lp_) return;
  B_ = batch;
  Lp_ = prefix_len;
  backend::Backend& be = *be_;
  const int64_t D = text_cfg_.hidden, E = expert_cfg_.hidden, C = spec_.chunk_size, A = spec_.max_action_dim;
  const int64_t kv_dim = text_cfg_.kv_heads * text_cfg_.head_dim;
  suffix_base_ = Lp_ + (pi05_ ? 0 : 1);
  prefix_x_ = be.alloc<float>(B_ * Lp_ * D);
  cache_.resize(be, vlm_.layers(), B_, suffix_base_ + C, kv_dim);
  prefix_pos_ = be.alloc<int64_t>(B_ * Lp_);
  prefix_mask_ = be.alloc<uint8_t>(B_ * Lp_ * Lp_);
  action_mask_ = be.alloc<uint8_t>(B_ * C * (suffix_base_ + C));
  action_pos_ = be.alloc<int64_t>(B_ * C);
  if (!pi05_) {
    state_ = be.alloc<float>(B_ * spec_.max_state_dim);
    state_x_ = be.alloc<float>(B_ * E);
    state_mask_ = be.alloc<uint8_t>(B_ * (Lp_ + 1));
    state_pos_ = be.alloc<int64_t>(B_);
  }
  x_t_ = be.alloc<float>(B_ * C * A);
  v_t_ = be.alloc<float>(B_ * C * A);
  suffix_x_ = be.alloc<float>(B_ * C * E);
  cat_ = be.alloc<float>(B_ * C * 2 * E);
  mlp_h_ = be.alloc<float>(B_ * C * E);
  normed_ = be.alloc<float>(B_ * C * E);
  time_emb_ = be.alloc<float>(E);
  time_h_ = be.alloc<float>(E);
  cond_ = be.alloc<float>(E);
}

// The text the tokenizer sees: pi0 appends a newline (Pi0NewLineProcessor); pi0.5 writes the state into the prompt
// (Pi05PrepareStateTokenizerProcessorStep), from the normalised, unpadded state.
std::string PiZero::prompt(const ModelInput& item) const {
  if (!pi05_) {
    const std::string& t = item.instruction;
    return !t.empty() && t.back() == '\n' ? t : t + "\n";
  }
  std::string cleaned = python_strip(item.instruction);
  std::replace(cleaned.begin(), cleaned.end(), '_', ' ');
  std::replace(cleaned.begin(), cleaned.end(), '\n', ' ');
  std::string state;
  for (float x : item.state) {
    if (!state.empty()) state += ' ';
    state += std::to_string(state_bin(x));
  }
  return "Task: " + cleaned + ", State: " + state + ";\nAction: ";
}

// The batch's token ids, padded to max_length: through the preprocessor's tokenizer settings (lerobot), or
// task_newline's ids padded on the right with id 0 and mask 0 (FluxVLA pads with pad_token_id 0).
text::BatchEncoding PiZero::encode_prompts(const std::vector<ModelInput>& batch, ModelOutput& out) const {
  if (pz_.prompt == PiZeroOptions::Prompt::lerobot) {
    std::vector<std::string> texts;
    for (const auto& item : batch) texts.push_back(prompt(item));
    text::BatchOptions opts = tokenizer_->defaults;
    opts.padding = tok_settings_.max_length_padding ? text::Padding::max_length : text::Padding::longest;
    opts.max_length = tok_settings_.max_length;
    opts.truncation = tok_settings_.truncation;
    opts.pad_right = tok_settings_.pad_right;
    return text::encode_batch(tokenizer_->tokenizer, texts, opts);
  }
  text::BatchEncoding enc;
  enc.batch = int64_t(batch.size());
  enc.length = tok_settings_.max_length;
  enc.ids.assign(std::size_t(enc.batch * enc.length), 0);
  enc.mask.assign(std::size_t(enc.batch * enc.length), 0);
  for (int64_t b = 0; b < enc.batch; ++b) {
    const TaskPrompt p = task_newline_prompt(*tokenizer_, batch[b].instruction, tok_settings_.max_length);
    if (p.wrote_special)
      out.warnings[b].push_back("the instruction writes a special token (<bos>, <eos>, <pad> or <unk>): it is encoded as "
                                "that token, while FluxVLA's SentencePiece encodes it as plain text");
    for (std::size_t j = 0; j < p.ids.size(); ++j) {
      enc.ids[b * enc.length + int64_t(j)] = p.ids[j];
      enc.mask[b * enc.length + int64_t(j)] = 1;
    }
  }
  return enc;
}

// One camera's frame into `out` (3 x H x W floats, CHW) as the checkpoint's convention prepares it.
void PiZero::prepare_image(const vision::Image& img, int64_t camera, float* out,
                           std::vector<std::string>& warnings) const {
  const int H = int(spec_.image_height), W = int(spec_.image_width);
  if (pz_.image_norm == PiZeroOptions::ImageNorm::lerobot) {
    vision::resize_with_pad_normalized(img, H, W, out, vision::TorchThreads::many, {}, 0.0f,
                                       vision::PadPlacement::centred);
    return;
  }
  const auto& mean = pz_.image_mean.size() == 1 ? pz_.image_mean[0] : pz_.image_mean.at(std::size_t(camera));
  const auto& stdev = pz_.image_std.size() == 1 ? pz_.image_std[0] : pz_.image_std.at(std::size_t(camera));
  const int64_t n = int64_t(H) * W;
  if (img.height <= 0 || img.width <= 0 || img.rgb.size() != std::size_t(img.height) * std::size_t(img.width) * 3)
    throw Error(ErrorCode::invalid_argument, "image for camera '" + spec_.cameras[std::size_t(camera)] +
                                                 "' has no pixels or a buffer that does not match its size");
  std::vector<float> resized;
  const float* src = nullptr;  // CHW 0..255 when resized
  if (img.height != H || img.width != W) {
    std::vector<float> chw(std::size_t(img.height) * std::size_t(img.width) * 3);
    const int64_t m = int64_t(img.height) * img.width;
    for (int c = 0; c < 3; ++c)
      for (int64_t i = 0; i < m; ++i) chw[std::size_t(c * m + i)] = float(img.rgb[std::size_t(i * 3 + c)]);
    resized.resize(std::size_t(3 * n));
    vision::resize_bilinear(chw.data(), 3, img.height, img.width, H, W, resized.data());
    src = resized.data();
    warnings.push_back("camera '" + spec_.cameras[std::size_t(camera)] + "': " + std::to_string(img.height) + "x" +
                       std::to_string(img.width) + " frame resized to " + std::to_string(H) + "x" + std::to_string(W) +
                       " with bilinear interpolation, not FluxVLA's PIL resize (send frames at the model's size)");
  }
  for (int c = 0; c < 3; ++c)
    for (int64_t i = 0; i < n; ++i) {
      const double x = src ? double(src[c * n + i]) : double(img.rgb[std::size_t(i * 3 + c)]);
      out[c * n + i] = float((x - mean[std::size_t(c)]) / stdev[std::size_t(c)]);
    }
}

void PiZero::build_prefix(const std::vector<ModelInput>& batch, ModelOutput& out) {
  backend::Backend& be = *be_;
  const auto t0 = std::chrono::steady_clock::now();
  const int64_t B = int64_t(batch.size()), D = text_cfg_.hidden;
  const int64_t H = spec_.image_height, W = spec_.image_width, ncam = int64_t(spec_.cameras.size());
  const int64_t img_elems = 3 * H * W;

  // Cameras: upstream puts a -1 image, masked out, in place of an absent camera. A masked token changes nothing for
  // the others (zero attention weight, no position), so here absent cameras simply have no slot in the prefix.
  host_pixels_.clear();
  std::vector<std::vector<int64_t>> item_images(B);  // per item: indices into the images run through the tower
  std::vector<int64_t> image_camera;
  for (int64_t c = 0; c < ncam; ++c) {
    for (int64_t b = 0; b < B; ++b) {
      auto it = batch[b].images.find(spec_.cameras[c]);
      if (it == batch[b].images.end()) continue;
      host_pixels_.resize(host_pixels_.size() + std::size_t(img_elems));
      prepare_image(it->second, c, host_pixels_.data() + host_pixels_.size() - img_elems, out.warnings[b]);
      item_images[b].push_back(int64_t(image_camera.size()));
      image_camera.push_back(c);
    }
  }
  for (int64_t b = 0; b < B; ++b) {
    if (item_images[b].empty())
      throw Error(ErrorCode::invalid_argument, "observation " + std::to_string(b) +
                                                   " has no image for any camera the model knows");
    // Slots in camera order (the loop above filled them camera-major).
    std::sort(item_images[b].begin(), item_images[b].end(),
              [&](int64_t x, int64_t y) { return image_camera[x] < image_camera[y]; });
    for (int64_t c = 0; c < ncam; ++c) {
      const bool synthetic = std::find(spec_.synthetic_cameras.begin(), spec_.synthetic_cameras.end(),
                                       spec_.cameras[c]) != spec_.synthetic_cameras.end();
      if (!synthetic && !batch[b].images.count(spec_.cameras[c]))
        out.warnings[b].push_back("no image for camera '" + spec_.cameras[c] + "': masked out, as upstream does");
    }
  }
  const int64_t images = int64_t(image_camera.size());
  if (pixels_.size() < int64_t(host_pixels_.size())) pixels_ = be.alloc<float>(int64_t(host_pixels_.size()));
  be.upload(host_pixels_.data(), int64_t(host_pixels_.size()), pixels_.at());

  // Language tokens: padded to max_length as upstream asks, then cut to the longest real row (the padding is masked).
  const text::BatchEncoding enc = encode_prompts(batch, out);
  const int64_t L = enc.length;
  for (int64_t id : enc.ids)
    if (id < 0 || id >= text_cfg_.vocab)
      throw Error(ErrorCode::internal, "token id " + std::to_string(id) + " outside the embedding table");
  token_ids_ = be.alloc<int64_t>(B * L);
  be.upload(enc.ids.data(), B * L, token_ids_.at());
  out.timings.set("preprocess", ms_since(t0));
  if (dumping()) {
    dump("pre.lang_tokens", Tensor{DType::i64, {B, L}, enc.ids.data(), nullptr});
    dump("pre.lang_mask", Tensor{DType::u8, {B, L}, enc.mask.data(), nullptr});
  }

  // Vision tower + projector over groups of up to kVisionGroup images.
  const auto t1 = std::chrono::steady_clock::now();
  const int64_t T = vision_.num_patches(H, W);
  constexpr int64_t kVisionGroup = 4;
  const int64_t group_rows = std::min(images, kVisionGroup) * T;
  if (vision_out_.size() < group_rows * vision_.hidden()) vision_out_ = be.alloc<float>(group_rows * vision_.hidden());
  if (img_tokens_.size() < images * T * D) img_tokens_ = be.alloc<float>(images * T * D);
  for (int64_t i = 0; i < images; i += kVisionGroup) {
    const int64_t n = std::min(kVisionGroup, images - i);
    vision_.forward(be, pixels_.at(i * img_elems), n, H, W, vision_out_.at());
    be.linear(*projector_, vision_out_.at(), n * T, img_tokens_.at(i * T * D));
  }
  images_run_ = images;
  be_->synchronize();  // a GPU runs behind the host: time the work, not its queueing
  out.timings.set("vision", ms_since(t1));
  if (dumping()) {
    for (int64_t c = 0; c < ncam; ++c) {
      // Only cameras every item has, in the [B, ...] layout of the oracle's intermediates.
      std::vector<int64_t> idx;
      for (int64_t i = 0; i < images; ++i)
        if (image_camera[i] == c) idx.push_back(i);
      if (int64_t(idx.size()) != B) continue;
      std::vector<float> px(std::size_t(B * img_elems)), tok(std::size_t(B * T * D));
      for (int64_t b = 0; b < B; ++b) {
        std::copy_n(&host_pixels_[idx[b] * img_elems], img_elems, &px[b * img_elems]);
        be.download(Ptr<const float>(img_tokens_.at(idx[b] * T * D)), T * D, &tok[b * T * D]);
      }
      dump("pre.pixels." + spec_.cameras[c], Tensor{DType::f32, {B, 3, H, W}, px.data(), nullptr});
      dump("mid.vision." + spec_.cameras[c], Tensor{DType::f32, {B, T, D}, tok.data(), nullptr});
    }
  }

  // Prefix per item: its image slots, then its real language tokens; rows padded to the longest with masked tokens.
  std::vector<int64_t> lang_len(B, 0);
  int64_t Lp = 0;
  for (int64_t b = 0; b < B; ++b) {
    for (int64_t j = 0; j < L; ++j) lang_len[b] += enc.mask[b * L + j];
    Lp = std::max(Lp, int64_t(item_images[b].size()) * T + lang_len[b]);
  }
  ensure_buffers(B, Lp);
  prefix_pad_.assign(std::size_t(B * Lp), 0);
  prefix_att_.assign(std::size_t(B * Lp), 0);  // one block: the prefix attends bidirectionally
  std::vector<float> zeros(std::size_t(Lp * D), 0.f);
  for (int64_t b = 0; b < B; ++b) {
    const Ptr<float> x = prefix_x_.at(b * Lp * D);
    int64_t t = 0;
    for (int64_t i : item_images[b]) {
      be.copy_rows(img_tokens_.at(i * T * D), 0, x + t * D, 0, 1, T * D);
      std::fill_n(&prefix_pad_[b * Lp + t], T, 1);
      t += T;
    }
    // Right padding puts the real tokens first; a left-padded row's real tokens are gathered from its end.
    const int64_t first = tok_settings_.pad_right ? 0 : L - lang_len[b];
    be.gather_rows(*embed_tokens_, token_ids_.at(b * L + first), lang_len[b], text_cfg_.embedding_scale, x + t * D);
    std::fill_n(&prefix_pad_[b * Lp + t], lang_len[b], 1);
    t += lang_len[b];
    if (t < Lp) be.upload(zeros.data(), (Lp - t) * D, x + t * D);
  }
  prefix_masks(prefix_pad_, prefix_att_, B, Lp, host_mask_, host_pos_);
  be.upload(host_mask_.data(), B * Lp * Lp, prefix_mask_.at());
  be.upload(host_pos_.data(), B * Lp, prefix_pos_.at());
  if (pi05_ && pz_.prompt == PiZeroOptions::Prompt::task_newline && dumping()) {
    // The normalised state, which this prompt does not carry (the model never sees it).
    std::vector<float> st;
    for (const auto& item : batch) st.insert(st.end(), item.state.begin(), item.state.end());
    dump("pre.state", Tensor{DType::f32, {B, spec_.state_dim}, st.data(), nullptr});
  } else if (pi05_ && dumping()) {
    // The normalised state and the bins the prompt carries.
    std::vector<float> st;
    std::vector<int64_t> bins;
    for (const auto& item : batch)
      for (float x : item.state) {
        st.push_back(x);
        bins.push_back(state_bin(x));
      }
    dump("pre.state", Tensor{DType::f32, {B, spec_.state_dim}, st.data(), nullptr});
    dump("pre.state_bins", Tensor{DType::i64, {B, spec_.state_dim}, bins.data(), nullptr});
  }
  if (!pi05_) {
    host_state_.assign(std::size_t(B * spec_.max_state_dim), 0.f);
    for (int64_t b = 0; b < B; ++b)
      std::copy(batch[b].state.begin(), batch[b].state.end(), &host_state_[b * spec_.max_state_dim]);
    be.upload(host_state_.data(), B * spec_.max_state_dim, state_.at());
    if (dumping()) dump("pre.state", Tensor{DType::f32, {B, spec_.max_state_dim}, host_state_.data(), nullptr});
  }
  if (dumping()) {
    dump_array<float>(*be_, "mid.prefix_embs", DType::f32, {B, Lp, D}, prefix_x_.at());
    dump("mid.prefix_pad_mask", Tensor{DType::u8, {B, Lp}, prefix_pad_.data(), nullptr});
  }
}

// The VLM over the prefix once (post-RoPE K/V of every layer into the cache); for pi0 then the state token through
// the expert, whose K/V do not depend on the actions or the time (it sees only the prefix and itself), so they are
// computed once and kept after the prefix's.
void PiZero::run_prefix() {
  backend::Backend& be = *be_;
  const int64_t B = B_, Lp = Lp_, C = spec_.chunk_size;
  const int64_t KvH = text_cfg_.kv_heads, hd = text_cfg_.head_dim;
  vlm_.forward(be, prefix_x_.at(), B, Lp, prefix_pos_.at(), prefix_mask_.at(), cache_);
  dump_prefix_kv(be, cache_.k, cache_.v, cache_.capacity, B, Lp, KvH, hd);
  std::vector<uint8_t> action_prefix_pad = prefix_pad_;
  int64_t action_prefix = Lp;
  if (!pi05_) {
    be.linear(*state_proj_, state_.at(), B, state_x_.at());
    block_suffix_masks(prefix_pad_, B, Lp, {1}, host_state_mask_, host_state_pos_);
    be.upload(host_state_mask_.data(), B * (Lp + 1), state_mask_.at());
    be.upload(host_state_pos_.data(), B, state_pos_.at());
    expert_.forward(be, state_x_.at(), B, 1, cache_, Lp, state_pos_.at(), state_mask_.at(), {}, {});
    // The actions see the state token as one more real prefix token.
    action_prefix_pad.assign(std::size_t(B * (Lp + 1)), 0);
    for (int64_t b = 0; b < B; ++b) {
      std::copy_n(&prefix_pad_[b * Lp], Lp, &action_prefix_pad[b * (Lp + 1)]);
      action_prefix_pad[b * (Lp + 1) + Lp] = 1;
    }
    action_prefix = Lp + 1;
  }
  // The action tokens are one attention block: each sees the prefix (and state) and every other action token.
  std::vector<int8_t> blocks(std::size_t(C), 0);
  blocks[0] = 1;
  block_suffix_masks(action_prefix_pad, B, action_prefix, blocks, host_action_mask_, host_action_pos_);
  be.upload(host_action_mask_.data(), B * C * (action_prefix + C), action_mask_.at());
  be.upload(host_action_pos_.data(), B * C, action_pos_.at());
}

void PiZero::time_sinusoid(float time) {
  backend::Backend& be = *be_;
  const int64_t E = expert_cfg_.hidden;
  if (pz_.float32_time) {
    const std::vector<float> emb = fluxvla_time_embedding(time, E, min_period_, max_period_);
    be.upload(emb.data(), E, time_emb_.at());
  } else {
    be.time_embedding(double(time), E, min_period_, max_period_, time_emb_.at());
  }
}

// silu(time_mlp_out(silu(time_mlp_in(t)))): one vector for the whole batch (every item is at the same time).
void PiZero::adarms_condition(float time) {
  backend::Backend& be = *be_;
  const int64_t E = expert_cfg_.hidden;
  time_sinusoid(time);
  be.linear(*time_in_, time_emb_.at(), 1, time_h_.at());
  be.activate(time_h_.at(), E, backend::Activation::silu);
  be.linear(*time_out_, time_h_.at(), 1, cond_.at());
  be.activate(cond_.at(), E, backend::Activation::silu);
}

Ptr<const float> PiZero::time_modulations(float time) {
  uint32_t key;
  std::memcpy(&key, &time, sizeof key);
  const int64_t layers_size = expert_.modulation_size();
  return time_modulations_.get(*be_, key, layers_size + 3 * expert_cfg_.hidden, [&](Ptr<float> mod) {
    adarms_condition(time);
    expert_.adaptive_modulations(*be_, cond_.at(), mod);
    be_->linear(*expert_norm_mod_, cond_.at(), 1, mod + layers_size);
  });
}

// One Euler step's velocity from x ([B, chunk, max_action_dim]) at `time`, into v (same layout).
void PiZero::denoise_step(Ptr<const float> x_t, float time, Ptr<float> v) {
  backend::Backend& be = *be_;
  const int64_t B = B_, C = spec_.chunk_size, E = expert_cfg_.hidden, rows = B * C;
  if (!pi05_) {
    // [action_in(x_t), time] -> action_time_mlp_in -> silu -> action_time_mlp_out.
    time_sinusoid(time);
    be.linear(*action_in_, x_t, rows, cat_.at(), false, /*ldy=*/2 * E);
    be.copy_rows(time_emb_.at(), 0, cat_.at(E), 2 * E, rows, E);
    be.linear(*time_in_, cat_.at(), rows, mlp_h_.at());
    be.activate(mlp_h_.at(), rows * E, backend::Activation::silu);
    be.linear(*time_out_, mlp_h_.at(), rows, suffix_x_.at());
    expert_.forward(be, suffix_x_.at(), B, C, cache_, suffix_base_, action_pos_.at(), action_mask_.at(), {}, {});
    be.rms_norm(suffix_x_.at(), rows, E, expert_norm_.at(), expert_cfg_.rms_norm_eps, normed_.at(),
                backend::RmsScale::one_plus_weight);
  } else {
    // The time alone conditions the adaptive norms.
    const Ptr<const float> mod = time_modulations(time);
    if (dumping() && time == 1.0f) {  // the first step's conditioning, one row per item as upstream holds it
      adarms_condition(time);
      std::vector<float> c(static_cast<std::size_t>(E)), rows_out;
      be.download(Ptr<const float>(cond_.at()), E, c.data());
      for (int64_t b = 0; b < B; ++b) rows_out.insert(rows_out.end(), c.begin(), c.end());
      dump("mid.adarms_cond.step0", Tensor{DType::f32, {B, E}, rows_out.data(), nullptr});
    }
    be.linear(*action_in_, x_t, rows, suffix_x_.at());
    expert_.forward(be, suffix_x_.at(), B, C, cache_, suffix_base_, action_pos_.at(), action_mask_.at(), {}, {}, mod);
    const Ptr<const float> final_mod = mod + expert_.modulation_size();
    be.rms_norm_modulated(suffix_x_.at(), rows, E, final_mod, final_mod + E, 0, rows, expert_cfg_.rms_norm_eps,
                          normed_.at());
  }
  be.linear(*action_out_, normed_.at(), rows, v);
}

double PiZero::flops(int64_t images, int64_t steps_run) const {
  const int64_t B = B_, C = spec_.chunk_size, Lp = Lp_, H = spec_.image_height, W = spec_.image_width;
  const int64_t patches = vision_.num_patches(H, W);
  double f = vision_.flops(images, H, W) + linear_flops(*projector_, images * patches) + vlm_.flops(B, Lp).total();
  if (!pi05_) f += linear_flops(*state_proj_, B) + expert_.forward_flops(B, 1, Lp);
  double step = linear_flops(*action_in_, B * C) + expert_.forward_flops(B, C, suffix_base_) +
                linear_flops(*action_out_, B * C);
  if (!pi05_) step += linear_flops(*time_in_, B * C) + linear_flops(*time_out_, B * C);
  return f + double(steps_run) * step;
}

ModelOutput PiZero::predict(const std::vector<ModelInput>& batch) {
  ModelOutput out = begin_predict(batch);
  build_prefix(batch, out);

  const auto t2 = std::chrono::steady_clock::now();
  run_prefix();
  be_->synchronize();  // a GPU runs behind the host: time the work, not its queueing
  out.timings.set("prefix", ms_since(t2));

  // Euler from the noise (t=1) to the actions (t=0), per-item controls (blocks/sampler.h).
  const int64_t B = int64_t(batch.size()), C = spec_.chunk_size, A = spec_.max_action_dim;
  std::function<void(Ptr<const float>)> on_step0;
  if (dumping()) on_step0 = [&](Ptr<const float> v) { dump_array<float>(*be_, "mid.velocity.step0", DType::f32, {B, C, A}, v); };
  sample_actions(*be_, batch, x_t_.at(), v_t_.at(), Schedule{1.0, 0.0, spec_.num_steps, pz_.float32_time},
                 [this](Ptr<const float> x, float time, Ptr<float> v) { denoise_step(x, time, v); }, on_step0, out);
  // Every item runs until the last one stops: the batch's steps are the most any item used.
  out.flops = flops(images_run_, *std::max_element(out.steps_used.begin(), out.steps_used.end()));
  return out;
}

}  // namespace

std::unique_ptr<Model> load_pi0(const fs::path& checkpoint_dir, const Json& config, TensorStore weights,
                                const LoadOptions& options) {
  return std::make_unique<PiZero>(checkpoint_dir, config, std::move(weights), options, /*pi05=*/false, PiZeroOptions{});
}

std::unique_ptr<Model> load_pi05(const fs::path& checkpoint_dir, const Json& config, TensorStore weights,
                                 const LoadOptions& options) {
  return std::make_unique<PiZero>(checkpoint_dir, config, std::move(weights), options, /*pi05=*/true, PiZeroOptions{});
}

std::unique_ptr<Model> load_pi05_with(const fs::path& checkpoint_dir, const Json& config, TensorStore weights,
                                      const LoadOptions& options, const PiZeroOptions& pizero) {
  return std::make_unique<PiZero>(checkpoint_dir, config, std::move(weights), options, /*pi05=*/true, pizero);
}

TaskPrompt task_newline_prompt(const text::PretrainedTokenizer& tokenizer, const std::string& task, int max_length) {
  if (!tokenizer.bos_token_id) throw Error(ErrorCode::format, tokenizer.source + ": no <bos> token");
  std::string cleaned = python_strip(task);
  std::replace(cleaned.begin(), cleaned.end(), '_', ' ');
  std::replace(cleaned.begin(), cleaned.end(), '\n', ' ');
  TaskPrompt p;
  p.ids.push_back(*tokenizer.bos_token_id);
  const std::vector<int32_t> text = tokenizer.tokenizer.encode(cleaned, /*add_special_tokens=*/false);
  const std::vector<int32_t> newline = tokenizer.tokenizer.encode("\n", /*add_special_tokens=*/false);
  p.ids.insert(p.ids.end(), text.begin(), text.end());
  p.ids.insert(p.ids.end(), newline.begin(), newline.end());
  for (const char* special : {"<bos>", "<eos>", "<pad>", "<unk>"})
    if (const auto id = tokenizer.tokenizer.token_to_id(special))
      p.wrote_special = p.wrote_special || std::find(text.begin(), text.end(), *id) != text.end();
  if (max_length > 0 && int64_t(p.ids.size()) > max_length) p.ids.resize(std::size_t(max_length));
  return p;
}

std::vector<float> fluxvla_time_embedding(float time, int64_t width, double min_period, double max_period) {
  if (width <= 0 || width % 2 != 0)
    throw Error(ErrorCode::invalid_argument, "time embedding width " + std::to_string(width) + " is not even");
  const int64_t half = width / 2;
  // torch.linspace(0, 1, half) in float32: step rounded to float32, then each value rounded once from
  // start + step * i (first half) or end - step * (half - 1 - i) (second half).
  const float step = half > 1 ? float(1.0) / float(half - 1) : 0.0f;
  const float min_p = float(min_period), ratio = float(max_period / min_period), pi_f = float(3.14159265358979323846);
  std::vector<float> out(static_cast<std::size_t>(width));
  for (int64_t i = 0; i < half; ++i) {
    const float fraction =
        half == 1 ? 0.0f : i < half / 2 ? float(double(step) * double(i)) : float(1.0 - double(step) * double(half - 1 - i));
    const float period = min_p * float(std::pow(double(ratio), double(fraction)));
    const float scale = (1.0f / period) * 2.0f * pi_f;
    const float arg = time * scale;
    out[std::size_t(i)] = std::sin(arg);
    out[std::size_t(half + i)] = std::cos(arg);
  }
  return out;
}

}  // namespace tether::models
