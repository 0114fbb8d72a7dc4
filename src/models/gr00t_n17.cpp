// GR00T N1.7 (see gr00t.h): the backbone per observation (frames, prompt, Qwen3-VL vision and text, VL self-attention),
// then the action head for the batch (state token, DiT over the flow-matching steps, per-embodiment decoder).
// docs/design/gr00t.md says what upstream computes and where.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>

#include "core/error.h"
#include "models/backbone.h"
#include "models/blocks/decoder.h"
#include "models/blocks/dit.h"
#include "models/blocks/linear.h"
#include "models/blocks/qwen3_vl_vision.h"
#include "models/gr00t.h"
#include "text/tokenizer.h"
#include "text/unicode.h"
#include "vision/gr00t_preprocess.h"

namespace tether::models {

namespace fs = std::filesystem;
using backend::Activation;
using backend::Ptr;

namespace {

constexpr const char* kVisual = "backbone.model.model.visual.";
constexpr const char* kText = "backbone.model.model.language_model.";
constexpr const char* kHead = "action_head.";

double elapsed_ms(std::chrono::steady_clock::time_point since) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - since).count();
}

// processor_config.json's processor_kwargs (the checkpoint's processing settings).
Json processor_kwargs(const fs::path& dir) {
  const fs::path p = dir / "processor_config.json";
  if (!fs::is_regular_file(p)) throw Error(ErrorCode::not_found, p.string() + ": missing (GR00T's processing settings)");
  const Json j = read_json_file(p.string());
  if (!j.contains("processor_kwargs") || !j.at("processor_kwargs").is_object())
    throw Error(ErrorCode::format, p.string() + ": no processor_kwargs object");
  return j.at("processor_kwargs");
}

// An enum string of the modality config ("ABSOLUTE", "absolute", "ActionRepresentation.ABSOLUTE") in lower case.
std::string enum_value(const Json& v) {
  if (!v.is_string()) return "";
  std::string s = v.get<std::string>();
  if (auto dot = s.rfind('.'); dot != std::string::npos) s = s.substr(dot + 1);
  std::transform(s.begin(), s.end(), s.begin(), [](unsigned char c) { return char(std::tolower(c)); });
  return s;
}

// The groups of one kind ("state" / "action") in modality-key order, with their bounds from statistics.json.
void read_groups(const Json& modality, const Json& stats, const std::string& kind, bool percentiles,
                 const std::string& where, std::vector<ModalityGroup>& groups, std::vector<float>& lo,
                 std::vector<float>& hi) {
  const Json keys = modality.contains(kind) ? modality.at(kind).value("modality_keys", Json::array()) : Json::array();
  if (!stats.contains(kind) || !stats.at(kind).is_object())
    throw Error(ErrorCode::format, where + ": statistics.json has no '" + kind + "' statistics for this embodiment");
  const Json& per_key = stats.at(kind);
  const char* lo_name = percentiles ? "q01" : "min";
  const char* hi_name = percentiles ? "q99" : "max";
  for (const Json& k : keys) {
    const std::string key = k.get<std::string>();
    if (!per_key.contains(key))
      throw Error(ErrorCode::format, where + ": statistics.json has no " + kind + " statistics for '" + key + "'");
    const Json& s = per_key.at(key);
    for (const char* name : {lo_name, hi_name})
      if (!s.contains(name) || !s.at(name).is_array())
        throw Error(ErrorCode::format, where + ": statistics for " + kind + " '" + key + "' have no " + name);
    const auto l = s.at(lo_name).get<std::vector<double>>(), h = s.at(hi_name).get<std::vector<double>>();
    if (l.size() != h.size() || l.empty())
      throw Error(ErrorCode::format, where + ": " + kind + " '" + key + "' has bounds of different or zero widths");
    groups.push_back({key, int64_t(l.size())});
    for (double v : l) lo.push_back(float(v));
    for (double v : h) hi.push_back(float(v));
  }
}

}  // namespace

bool gr00t_applies_libero_transform(const std::string& embodiment_tag) { return embodiment_tag == "libero_sim"; }

void libero_gripper_transform(std::vector<float>& actions, const std::vector<ModalityGroup>& action_groups) {
  int64_t start = 0, width = 0, dim = 0;
  for (const auto& g : action_groups) {
    if (g.name == "gripper") start = dim, width = g.dim;
    dim += g.dim;
  }
  if (width == 0 || dim == 0) return;
  for (std::size_t r = 0; r * std::size_t(dim) < actions.size(); ++r)
    for (int64_t c = start; c < start + width; ++c) {
      float& g = actions[r * std::size_t(dim) + std::size_t(c)];
      const float s = 2.0f * g - 1.0f;
      g = -float((s > 0) - (s < 0));
    }
}

Gr00tEmbodiment read_gr00t_embodiment(const fs::path& dir, const std::string& wanted) {
  const Json kwargs = processor_kwargs(dir);
  const std::string where = (dir / "processor_config.json").string();
  if (!kwargs.contains("modality_configs") || !kwargs.at("modality_configs").is_object() ||
      kwargs.at("modality_configs").empty())
    throw Error(ErrorCode::format, where + ": processor_kwargs has no modality_configs");
  const Json& modalities = kwargs.at("modality_configs");
  std::string known;
  for (auto it = modalities.begin(); it != modalities.end(); ++it) known += (known.empty() ? "" : ", ") + it.key();
  std::string tag = wanted;
  if (tag.empty()) {
    if (modalities.size() != 1)
      throw Error(ErrorCode::invalid_argument, dir.string() + " holds several embodiments; name the one served with --embodiment-tag (" + known + ")");
    tag = modalities.begin().key();
  }
  if (!modalities.contains(tag))
    throw Error(ErrorCode::invalid_argument, "unknown embodiment tag '" + tag + "' (" + dir.string() + " has: " +
                                                 known + ")");
  Gr00tEmbodiment e;
  e.tag = tag;
  const Json& m = modalities.at(tag);

  const fs::path ids_path = dir / "embodiment_id.json";
  if (!fs::is_regular_file(ids_path))
    throw Error(ErrorCode::not_found, ids_path.string() + ": missing (which weights row each embodiment uses)");
  const Json ids = read_json_file(ids_path.string());
  if (!ids.contains(tag) || !ids.at(tag).is_number_integer())
    throw Error(ErrorCode::format, ids_path.string() + ": no row for embodiment '" + tag + "'");
  e.id = ids.at(tag).get<int64_t>();

  const Json video = m.value("video", Json::object());
  for (const Json& k : video.value("modality_keys", Json::array())) e.cameras.push_back(k.get<std::string>());
  if (e.cameras.empty()) throw Error(ErrorCode::format, where + ": embodiment '" + tag + "' has no cameras");
  if (video.value("delta_indices", Json::array({0})).size() != 1)
    throw Error(ErrorCode::unsupported, where + ": embodiment '" + tag + "' takes several frames per camera");

  const Json action = m.value("action", Json::object());
  e.action_horizon = int64_t(action.value("delta_indices", Json::array()).size());
  if (e.action_horizon <= 0) throw Error(ErrorCode::format, where + ": embodiment '" + tag + "' has no action steps");
  for (const Json& c : action.value("action_configs", Json::array()))
    if (enum_value(c.value("rep", Json("absolute"))) == "relative")
      throw Error(ErrorCode::unsupported, where + ": embodiment '" + tag +
                                              "' has relative actions, which Tether does not decode yet");
  if (json_get_or<bool>(kwargs, "use_relative_action", false, where))
    throw Error(ErrorCode::unsupported, where + ": use_relative_action is not supported yet");

  const fs::path stats_path = dir / "statistics.json";
  if (!fs::is_regular_file(stats_path))
    throw Error(ErrorCode::not_found, stats_path.string() + ": missing (GR00T's normalisation statistics)");
  const Json stats = read_json_file(stats_path.string());
  if (!stats.contains(tag)) throw Error(ErrorCode::format, stats_path.string() + ": no statistics for '" + tag + "'");
  const bool percentiles = json_get_or<bool>(kwargs, "use_percentiles", true, where);
  read_groups(m, stats.at(tag), "state", percentiles, stats_path.string(), e.state_groups, e.state_lo, e.state_hi);
  read_groups(m, stats.at(tag), "action", percentiles, stats_path.string(), e.action_groups, e.action_lo, e.action_hi);
  return e;
}

std::string gr00t_formalize_language(const std::string& instruction, bool formalize) {
  std::string text = instruction.empty() ? "Perform the task." : instruction;
  if (!formalize) return text;
  const std::string lower = text::lowercase(text);
  std::string out;
  for (std::size_t i = 0; i < lower.size();) {
    std::size_t n = 0;
    const char32_t c = text::decode_utf8(lower, i, n);
    if (text::is_python_alnum(c) || text::is_python_space(c) || c == U'_') out.append(lower, i, n);
    i += n;
  }
  return out;
}

namespace {

struct HeadConfig {
  int64_t select_layer = 16, backbone_dim = 2048, hidden = 1024, input_dim = 1536, max_state_dim = 132,
          max_action_dim = 132, action_horizon = 40, num_embodiments = 32, max_seq_len = 1024, steps = 4,
          buckets = 1000;
  float rtc_ramp_rate = 6.0f;
  bool add_pos_embed = true, use_vlln = true;
  DitConfig dit;
  int64_t vl_layers = 0, vl_heads = 0, vl_head_dim = 0;
  std::string model_name;

  static HeadConfig from_json(const Json& c, const std::string& where) {
    HeadConfig h;
    h.select_layer = json_get_or<int64_t>(c, "select_layer", h.select_layer, where);
    h.backbone_dim = json_get_or<int64_t>(c, "backbone_embedding_dim", h.backbone_dim, where);
    h.hidden = json_get_or<int64_t>(c, "hidden_size", h.hidden, where);
    h.input_dim = json_get_or<int64_t>(c, "input_embedding_dim", h.input_dim, where);
    h.max_state_dim = json_get_or<int64_t>(c, "max_state_dim", h.max_state_dim, where);
    h.max_action_dim = json_get_or<int64_t>(c, "max_action_dim", h.max_action_dim, where);
    h.action_horizon = json_get_or<int64_t>(c, "action_horizon", h.action_horizon, where);
    h.num_embodiments = json_get_or<int64_t>(c, "max_num_embodiments", h.num_embodiments, where);
    h.max_seq_len = json_get_or<int64_t>(c, "max_seq_len", h.max_seq_len, where);
    h.steps = json_get_or<int64_t>(c, "num_inference_timesteps", h.steps, where);
    h.buckets = json_get_or<int64_t>(c, "num_timestep_buckets", h.buckets, where);
    h.rtc_ramp_rate = float(json_get_or<double>(c, "rtc_ramp_rate", h.rtc_ramp_rate, where));
    h.add_pos_embed = json_get_or<bool>(c, "add_pos_embed", true, where);
    h.use_vlln = json_get_or<bool>(c, "use_vlln", true, where);
    h.model_name = json_get_or<std::string>(c, "model_name", "nvidia/Cosmos-Reason2-2B", where);
    if (json_get_or<int64_t>(c, "state_history_length", 1, where) != 1)
      throw Error(ErrorCode::unsupported, where + ": state_history_length other than 1");
    const bool alternate = json_get_or<bool>(c, "use_alternate_vl_dit", true, where);
    h.dit = DitConfig::from_json(c.value("diffusion_model_cfg", Json::object()), h.backbone_dim, alternate,
                                 json_get_or<int64_t>(c, "attend_text_every_n_blocks", 2, where),
                                 where + ": diffusion_model_cfg");
    const Json vl = c.value("vl_self_attention_cfg", Json::object());
    if (!vl.is_null()) {
      h.vl_layers = json_get_or<int64_t>(vl, "num_layers", 0, where);
      h.vl_heads = json_get_or<int64_t>(vl, "num_attention_heads", 8, where);
      h.vl_head_dim = json_get_or<int64_t>(vl, "attention_head_dim", 64, where);
    }
    if (h.dit.dim() != h.input_dim)
      throw Error(ErrorCode::format, where + ": the DiT width " + std::to_string(h.dit.dim()) +
                                         " is not input_embedding_dim " + std::to_string(h.input_dim));
    if (h.dit.output_dim != h.hidden)
      throw Error(ErrorCode::format, where + ": the DiT output_dim is not hidden_size");
    if (h.vl_layers > 0 && h.vl_heads * h.vl_head_dim != h.backbone_dim)
      throw Error(ErrorCode::format, where + ": vl_self_attention_cfg's width is not backbone_embedding_dim");
    if (h.add_pos_embed && h.max_seq_len < h.action_horizon)
      throw Error(ErrorCode::format, where + ": max_seq_len is below action_horizon");
    if (h.steps < 1) throw Error(ErrorCode::format, where + ": num_inference_timesteps must be >= 1");
    return h;
  }
};

// A category-specific linear layer (`W` [categories, in, out], `b` [categories, out]) for one category, packed as an
// ordinary linear layer (its W is stored input-major, the transpose of nn.Linear's).
std::unique_ptr<backend::LinearWeights> load_category_linear(backend::Backend& be, Weights& w, const std::string& name,
                                                             int64_t categories, int64_t in, int64_t out, int64_t id,
                                                             cpu::Precision precision) {
  if (id < 0 || id >= categories)
    throw Error(ErrorCode::format, name + ": embodiment row " + std::to_string(id) + " is outside its " +
                                       std::to_string(categories) + " rows");
  const float* W = w.f32(name + ".W", {categories, in, out}) + id * in * out;
  const float* b = w.f32(name + ".b", {categories, out}) + id * out;
  std::vector<float> t(static_cast<std::size_t>(in * out));
  for (int64_t i = 0; i < in; ++i)
    for (int64_t o = 0; o < out; ++o) t[std::size_t(o * in + i)] = W[i * out + o];
  return be.pack_linear(t.data(), out, in, b, precision);
}

class Gr00tN17 final : public Model {
 public:
  Gr00tN17(const fs::path& dir, const Json& config, TensorStore store, const LoadOptions& options);
  const ModelSpec& spec() const override { return spec_; }
  ModelOutput predict(const std::vector<ModelInput>& batch) override;

 private:
  struct Prefix {  // one observation's backbone output
    int64_t len = 0;
    backend::Array<float> vl;         // [len, backbone_dim]: vl_embeds
    std::vector<uint8_t> image_mask;  // [len]: 1 on image tokens
  };
  Prefix encode_observation(const ModelInput& in, int64_t item, ModelOutput& out);
  std::vector<int32_t> prompt_ids(const std::string& instruction, const std::vector<int64_t>& tokens_per_image) const;
  void rope_tables(const std::vector<int32_t>& ids, const std::vector<vision::PatchGrid>& grids,
                   std::vector<float>& cos, std::vector<float>& sin, std::vector<int64_t>& positions) const;
  void velocity(int64_t B, Ptr<const float> x, float time, Ptr<float> v);

  std::shared_ptr<backend::Backend> be_;
  std::unique_ptr<Weights> weights_;
  ModelSpec spec_;
  HeadConfig head_;
  Gr00tEmbodiment embodiment_;
  vision::Gr00tImageGeometry geometry_;
  vision::QwenImageConfig qwen_;
  bool formalize_ = true;
  std::unique_ptr<text::PretrainedTokenizer> tokenizer_;
  int32_t image_token_ = 0, vision_start_ = 0, vision_end_ = 0, im_start_ = 0, im_end_ = 0;

  Qwen3VisionTower vision_;
  DecoderConfig text_cfg_;
  DecoderStack text_;
  std::unique_ptr<backend::Table> embed_;
  float rope_theta_ = 5000000.0f;
  std::vector<int64_t> mrope_section_;
  backend::Array<float> vlln_w_, vlln_b_;
  SelfAttentionStack vl_attention_;
  DiTStack dit_;
  std::unique_ptr<backend::LinearWeights> state1_, state2_, act1_, act2_, act3_, dec1_, dec2_;
  backend::Array<float> action_pos_;  // [action_horizon, input_dim]

  // Per-request buffers, grown once per shape.
  backend::Array<float> pixels_, merged_, x_, rope_cos_, rope_sin_, context_, state_, state_mid_, state_tok_;
  std::vector<backend::Array<float>> deepstack_;
  backend::Array<int64_t> ids_;
  backend::Array<uint8_t> causal_, text_keys_, image_keys_, all_keys_;
  backend::Array<float> noise_x_, noise_v_, act_in_, act_mid_, tokens_, dit_out_, dec_mid_, dec_out_, temb_;
  std::vector<CrossKv> kv_;
  std::vector<Ptr<const uint8_t>> dit_masks_;
  std::vector<float> host_sinusoid_;  // the action encoder's time row, reused by every step  // per DiT block: the key mask of this request's context (cross blocks)
};

void grow(backend::Backend& be, backend::Array<float>& a, int64_t n) {
  if (a.size() < n) a = be.alloc<float>(n);
}

Gr00tN17::Gr00tN17(const fs::path& dir, const Json& config, TensorStore store, const LoadOptions& options)
    : be_(options.backend ? options.backend : backend::make_backend("cpu")) {
  const std::string where = (dir / "config.json").string();
  backend::Backend& be = *be_;
  const cpu::Precision precision = options.precision;
  head_ = HeadConfig::from_json(config, where);
  embodiment_ = read_gr00t_embodiment(dir, options.embodiment);
  const Json kwargs = processor_kwargs(dir);
  const std::string pwhere = (dir / "processor_config.json").string();
  geometry_ = vision::Gr00tImageGeometry::from_processor_kwargs(kwargs, pwhere);
  formalize_ = json_get_or<bool>(kwargs, "formalize_language", true, pwhere);
  if (!json_get_or<bool>(kwargs, "clip_outliers", true, pwhere))
    throw Error(ErrorCode::unsupported, pwhere + ": clip_outliers false is not supported yet");

  // The backbone repository the config names: its architecture, tokenizer and image processor settings.
  const fs::path bdir = find_backbone_dir(dir, head_.model_name, "model_name in config.json");
  const std::string bwhere = (bdir / "config.json").string();
  const Json bcfg = read_json_file(bwhere);
  const Json text_json = bcfg.value("text_config", Json::object());
  text_cfg_ = DecoderConfig::from_llama_json(text_json, bwhere + ": text_config");
  text_cfg_.qk_norm = true;
  rope_theta_ = json_get_or<float>(text_json, "rope_theta", 5000000.0f, bwhere);
  Json rope = text_json.value("rope_scaling", Json(nullptr));
  if (rope.is_null()) rope = text_json.value("rope_parameters", Json::object());
  if (rope.contains("rope_theta")) rope_theta_ = rope.at("rope_theta").get<float>();
  mrope_section_ = rope.value("mrope_section", std::vector<int64_t>{24, 20, 20});
  if (!rope.value("mrope_interleaved", true))
    throw Error(ErrorCode::unsupported, bwhere + ": only the interleaved multimodal RoPE is supported");
  if (mrope_section_.size() != 3 || mrope_section_[0] + mrope_section_[1] + mrope_section_[2] != text_cfg_.head_dim / 2)
    throw Error(ErrorCode::format, bwhere + ": mrope_section does not add up to head_dim / 2");
  if (head_.select_layer < 1 || head_.select_layer > text_cfg_.layers)
    throw Error(ErrorCode::format, where + ": select_layer " + std::to_string(head_.select_layer) + " is outside the " +
                                       std::to_string(text_cfg_.layers) + " text layers");
  if (text_cfg_.hidden != head_.backbone_dim)
    throw Error(ErrorCode::format, where + ": backbone_embedding_dim is not the text model's width");
  const Qwen3VisionConfig vcfg = Qwen3VisionConfig::from_json(bcfg.value("vision_config", Json::object()),
                                                              bwhere + ": vision_config");
  if (vcfg.out_hidden != text_cfg_.hidden)
    throw Error(ErrorCode::format, bwhere + ": vision out_hidden_size is not the text width");
  image_token_ = json_get<int32_t>(bcfg, "image_token_id", bwhere);
  vision_start_ = json_get<int32_t>(bcfg, "vision_start_token_id", bwhere);
  vision_end_ = json_get<int32_t>(bcfg, "vision_end_token_id", bwhere);
  const fs::path pp = bdir / "preprocessor_config.json";
  qwen_ = fs::is_regular_file(pp) ? vision::QwenImageConfig::from_json(read_json_file(pp.string()), pp.string())
                                  : vision::QwenImageConfig{};
  if (qwen_.patch_size != vcfg.patch || qwen_.merge_size != vcfg.merge || qwen_.temporal_patch_size != vcfg.temporal_patch)
    throw Error(ErrorCode::format, pp.string() + ": patch, merge or temporal sizes differ from the vision tower's");
  tokenizer_ = std::make_unique<text::PretrainedTokenizer>(text::load_pretrained_tokenizer(bdir.string()));
  auto special = [&](const char* token) {
    const auto id = tokenizer_->tokenizer.token_to_id(token);
    if (!id) throw Error(ErrorCode::format, tokenizer_->source + ": no token " + token);
    return *id;
  };
  im_start_ = special("<|im_start|>");
  im_end_ = special("<|im_end|>");
  if (special("<|image_pad|>") != image_token_ || special("<|vision_start|>") != vision_start_ ||
      special("<|vision_end|>") != vision_end_)
    throw Error(ErrorCode::format, tokenizer_->source + ": the image tokens' ids differ from " + bwhere);

  // Kept for the model's life: constants (norms, biases, tables) are views of its mapping or of its widened copies.
  weights_ = std::make_unique<Weights>(std::move(store));
  Weights& w = *weights_;
  vision_.load(be, w, kVisual, vcfg, precision);
  embed_ = be.table(w.raw(std::string(kText) + "embed_tokens.weight", {text_cfg_.vocab, text_cfg_.hidden}));
  text_.load(be, w, std::string(kText) + "layers.", text_cfg_, head_.select_layer, precision, false);
  const int64_t D = head_.backbone_dim, Din = head_.input_dim, Hd = head_.hidden;
  if (head_.use_vlln) {
    vlln_w_ = be.constant(w.f32(std::string(kHead) + "vlln.weight", {D}), D);
    vlln_b_ = be.constant(w.f32(std::string(kHead) + "vlln.bias", {D}), D);
  }
  vl_attention_.load(be, w, std::string(kHead) + "vl_self_attention.", head_.vl_layers, head_.vl_heads,
                     head_.vl_head_dim, precision);
  dit_.load(be, w, std::string(kHead) + "model.", head_.dit, precision);
  const int64_t C = head_.num_embodiments, id = embodiment_.id, S = head_.max_state_dim, A = head_.max_action_dim;
  const std::string h = kHead;
  state1_ = load_category_linear(be, w, h + "state_encoder.layer1", C, S, Hd, id, precision);
  state2_ = load_category_linear(be, w, h + "state_encoder.layer2", C, Hd, Din, id, precision);
  act1_ = load_category_linear(be, w, h + "action_encoder.W1", C, A, Din, id, precision);
  act2_ = load_category_linear(be, w, h + "action_encoder.W2", C, 2 * Din, Din, id, precision);
  act3_ = load_category_linear(be, w, h + "action_encoder.W3", C, Din, Din, id, precision);
  dec1_ = load_category_linear(be, w, h + "action_decoder.layer1", C, Hd, Hd, id, precision);
  dec2_ = load_category_linear(be, w, h + "action_decoder.layer2", C, Hd, A, id, precision);
  if (head_.add_pos_embed)
    action_pos_ = be.constant(w.f32(h + "position_embedding.weight", {head_.max_seq_len, Din}), head_.action_horizon * Din);

  spec_.family = gr00t_n17_family().name;
  spec_.stages = gr00t_n17_family().stages;
  spec_.missing_camera_rule = gr00t_n17_family().missing_camera_rule;
  spec_.tokenizer = tokenizer_kind_name(gr00t_n17_family().tokenizer);
  spec_.tokenizer_source = tokenizer_->source;
  spec_.embodiment = embodiment_.tag;
  spec_.cameras = embodiment_.cameras;
  spec_.every_camera_required = true;
  spec_.state_key = "state";
  spec_.action_key = "action";
  spec_.state_groups = embodiment_.state_groups;
  spec_.action_groups = embodiment_.action_groups;
  for (const auto& g : spec_.state_groups) spec_.state_dim += g.dim;
  for (const auto& g : spec_.action_groups) spec_.action_dim += g.dim;
  spec_.max_state_dim = S;
  spec_.max_action_dim = A;
  spec_.chunk_size = std::min(embodiment_.action_horizon, head_.action_horizon);
  spec_.sampled_chunk = head_.action_horizon;
  spec_.num_steps = head_.steps;
  spec_.rtc = RtcMethod::inpainting;  // N1.7's own real-time chunking (sampler.h)
  spec_.rtc_ramp_rate = head_.rtc_ramp_rate;
  spec_.image_height = geometry_.target_h;
  spec_.image_width = geometry_.target_w;
  spec_.precision = precision;
  spec_.weights_dtype = w.stored_dtype();
  if (spec_.state_dim > S || spec_.action_dim > A)
    throw Error(ErrorCode::format, where + ": embodiment '" + embodiment_.tag + "' has more state or action values than "
                                           "max_state_dim / max_action_dim");
  w.finish_loading();
}

std::vector<int32_t> Gr00tN17::prompt_ids(const std::string& instruction,
                                          const std::vector<int64_t>& tokens_per_image) const {
  // One user message, the images first, as the chat template renders it; each image pad repeated per image token.
  const text::Tokenizer& t = tokenizer_->tokenizer;
  std::vector<int32_t> ids = {im_start_};
  for (int32_t id : t.encode("user\n", false)) ids.push_back(id);
  for (int64_t n : tokens_per_image) {
    ids.push_back(vision_start_);
    ids.insert(ids.end(), std::size_t(n), image_token_);
    ids.push_back(vision_end_);
  }
  for (int32_t id : t.encode(gr00t_formalize_language(instruction, formalize_), false)) ids.push_back(id);
  ids.push_back(im_end_);
  for (int32_t id : t.encode("\n", false)) ids.push_back(id);
  return ids;
}

void Gr00tN17::rope_tables(const std::vector<int32_t>& ids, const std::vector<vision::PatchGrid>& grids,
                           std::vector<float>& cos, std::vector<float>& sin, std::vector<int64_t>& positions) const {
  // Three position rows (time, height, width): text counts up on all three; an image's tokens share the time, take
  // their merged row / column as offsets, and the text after it starts past the larger side.
  const int64_t L = int64_t(ids.size()), m = qwen_.merge_size;
  positions.assign(std::size_t(3 * L), 0);
  int64_t cur = 0;
  std::size_t image = 0;
  for (int64_t i = 0; i < L;) {
    if (ids[std::size_t(i)] != image_token_) {
      for (int r = 0; r < 3; ++r) positions[std::size_t(r * L + i)] = cur;
      ++cur, ++i;
      continue;
    }
    if (image >= grids.size()) throw Error(ErrorCode::internal, "gr00t: more image runs than images");
    const int64_t gh = grids[image].h / m, gw = grids[image].w / m;
    for (int64_t r = 0; r < gh; ++r)
      for (int64_t c = 0; c < gw; ++c, ++i) {
        positions[std::size_t(i)] = cur;
        positions[std::size_t(L + i)] = cur + r;
        positions[std::size_t(2 * L + i)] = cur + c;
      }
    cur += std::max(gh, gw);
    ++image;
  }
  // Interleaved M-RoPE: frequency j turns with the height when j % 3 == 1 and with the width when j % 3 == 2, within
  // their sections; every other frequency with the time.
  const int64_t half = text_cfg_.head_dim / 2;
  std::vector<float> inv_freq(static_cast<std::size_t>(half));
  for (int64_t j = 0; j < half; ++j)
    inv_freq[std::size_t(j)] =
        1.0f / float(std::pow(double(rope_theta_), double(float(2 * j) / float(text_cfg_.head_dim))));
  cos.assign(std::size_t(L * half), 0.f);
  sin.assign(std::size_t(L * half), 0.f);
  for (int64_t i = 0; i < L; ++i)
    for (int64_t j = 0; j < half; ++j) {
      int row = 0;
      if (j % 3 == 1 && j < 3 * mrope_section_[1]) row = 1;
      if (j % 3 == 2 && j < 3 * mrope_section_[2]) row = 2;
      const float angle = float(positions[std::size_t(row * L + i)]) * inv_freq[std::size_t(j)];
      cos[std::size_t(i * half + j)] = std::cos(angle);
      sin[std::size_t(i * half + j)] = std::sin(angle);
    }
}

Gr00tN17::Prefix Gr00tN17::encode_observation(const ModelInput& in, int64_t item, ModelOutput& out) {
  backend::Backend& be = *be_;
  auto t0 = std::chrono::steady_clock::now();
  // Frames: every camera of the embodiment, in its order (upstream has no rule for a missing one).
  std::vector<vision::PixelPatches> frames;
  std::vector<vision::PatchGrid> grids;
  std::vector<int64_t> tokens_per_image;
  int64_t rows = 0;
  for (const std::string& cam : spec_.cameras) {
    auto it = in.images.find(cam);
    if (it == in.images.end())
      throw Error(ErrorCode::invalid_argument, "observation " + std::to_string(item) + ": no image for camera '" + cam +
                                                   "' (GR00T needs every camera of its embodiment)");
    frames.push_back(vision::gr00t_preprocess_frame(it->second, geometry_, qwen_));
    grids.push_back(frames.back().grid);
    tokens_per_image.push_back(frames.back().grid.patches() / (qwen_.merge_size * qwen_.merge_size));
    rows += frames.back().grid.patches();
  }
  const int64_t row_size = qwen_.row_size();
  std::vector<float> host_pixels;
  host_pixels.reserve(std::size_t(rows * row_size));
  for (const auto& f : frames) host_pixels.insert(host_pixels.end(), f.values.begin(), f.values.end());
  const std::vector<int32_t> ids = prompt_ids(in.instruction, tokens_per_image);
  const int64_t L = int64_t(ids.size()), D = text_cfg_.hidden, M = rows / (qwen_.merge_size * qwen_.merge_size);
  std::vector<float> cs, sn;
  std::vector<int64_t> positions;
  rope_tables(ids, grids, cs, sn, positions);
  if (dumping()) {
    dump("pre.pixel_values", Tensor{DType::f32, {rows, row_size}, host_pixels.data(), nullptr});
    std::vector<int64_t> ids64(ids.begin(), ids.end());
    dump("pre.input_ids", Tensor{DType::i64, {1, L}, ids64.data(), nullptr});
    dump("mid.position_ids", Tensor{DType::i64, {3, 1, L}, positions.data(), nullptr});
  }
  out.timings.set("preprocess", out.timings.get("preprocess") + elapsed_ms(t0));

  // Vision: merged image rows and the DeepStack features.
  t0 = std::chrono::steady_clock::now();
  grow(be, pixels_, rows * row_size);
  be.upload(host_pixels.data(), rows * row_size, pixels_.at());
  grow(be, merged_, M * D);
  deepstack_.resize(std::size_t(vision_.deepstack_count()));
  std::vector<Ptr<float>> ds;
  for (auto& a : deepstack_) {
    grow(be, a, M * D);
    ds.push_back(a.at());
  }
  std::vector<VisionGrid> vgrids;
  for (const auto& g : grids) vgrids.push_back({g.t, g.h, g.w});
  backend::Array<float> patch_dump;
  if (dumping()) patch_dump = be.alloc<float>(rows * vision_.config().hidden);
  vision_.forward(be, pixels_.at(), vgrids, merged_.at(), ds, dumping() ? patch_dump.at() : Ptr<float>());
  if (dumping()) {
    dump_array<float>(be, "mid.vision.embeddings", DType::f32, {rows, vision_.config().hidden}, patch_dump.at());
    dump_array<float>(be, "mid.vision.merged", DType::f32, {M, D}, merged_.at());
    for (std::size_t k = 0; k < ds.size(); ++k)
      dump_array<float>(be, "mid.vision.deepstack." + std::to_string(k), DType::f32, {M, D}, ds[k]);
  }
  out.timings.set("vision", out.timings.get("vision") + elapsed_ms(t0));

  // Text: token embeddings with the image rows in place of the image pads, the decoder with the DeepStack features
  // added after its first layers, then the VL norm and self-attention.
  t0 = std::chrono::steady_clock::now();
  grow(be, x_, L * D);
  if (ids_.size() < L) ids_ = be.alloc<int64_t>(L);
  const std::vector<int64_t> ids64(ids.begin(), ids.end());
  be.upload(ids64.data(), L, ids_.at());
  be.gather_rows(*embed_, ids_.at(), L, 1.0f, x_.at());
  std::vector<std::pair<int64_t, int64_t>> image_runs;  // (first token, length)
  Prefix p;
  p.len = L;
  p.vl = be.alloc<float>(L * D);
  const Ptr<float> vl_out = p.vl.at();
  p.image_mask.assign(std::size_t(L), 0);
  for (int64_t i = 0; i < L;) {
    if (ids[std::size_t(i)] != image_token_) {
      ++i;
      continue;
    }
    int64_t j = i;
    while (j < L && ids[std::size_t(j)] == image_token_) p.image_mask[std::size_t(j++)] = 1;
    image_runs.emplace_back(i, j - i);
    i = j;
  }
  int64_t image_row = 0;
  for (const auto& [first, n] : image_runs) {
    be.copy_rows(merged_.at(image_row * D), D, x_.at(first * D), D, n, D);
    image_row += n;
  }
  if (image_row != M) throw Error(ErrorCode::internal, "gr00t: image tokens and image rows differ");
  if (dumping()) dump_array<float>(be, "mid.llm.inputs_embeds", DType::f32, {1, L, D}, x_.at());

  grow(be, rope_cos_, L * text_cfg_.head_dim / 2);
  grow(be, rope_sin_, L * text_cfg_.head_dim / 2);
  be.upload(cs.data(), int64_t(cs.size()), rope_cos_.at());
  be.upload(sn.data(), int64_t(sn.size()), rope_sin_.at());
  std::vector<uint8_t> causal(std::size_t(L * L), 0);
  for (int64_t i = 0; i < L; ++i)
    for (int64_t j = 0; j <= i; ++j) causal[std::size_t(i * L + j)] = 1;
  if (causal_.size() < L * L) causal_ = be.alloc<uint8_t>(L * L);
  be.upload(causal.data(), L * L, causal_.at());
  KvCache cache;
  cache.resize(be, text_.layers(), 1, L, text_cfg_.kv_heads * text_cfg_.head_dim);
  const int64_t layers = text_.layers();
  const auto after_layer = [&](int64_t layer) {
    if (dumping()) dump_array<float>(be, "mid.llm.layer." + std::to_string(layer), DType::f32, {1, L, D}, x_.at());
    // The feature is the last kept layer's output as it returns, so nothing is added after that one.
    if (layer + 1 >= layers || layer >= int64_t(ds.size())) return;
    int64_t row = 0;
    for (const auto& [first, n] : image_runs) {
      be.add(x_.at(first * D), Ptr<const float>(ds[std::size_t(layer)] + row * D), n * D, x_.at(first * D));
      row += n;
    }
  };
  text_.forward(be, x_.at(), 1, L, RotaryTable{rope_cos_.at(), rope_sin_.at()}, causal_.at(), cache, after_layer);
  if (dumping()) dump_array<float>(be, "mid.backbone_features", DType::f32, {1, L, D}, x_.at());
  if (head_.use_vlln) be.layer_norm(x_.at(), L, D, vlln_w_.at(), vlln_b_.at(), 1e-5f, vl_out);
  else be.copy_rows(x_.at(), D, vl_out, D, L, D);
  if (dumping()) dump_array<float>(be, "mid.vl_embeds.vlln", DType::f32, {1, L, D}, vl_out);
  vl_attention_.forward(be, vl_out, 1, L);
  if (dumping()) dump_array<float>(be, "mid.vl_embeds", DType::f32, {1, L, D}, vl_out);
  out.timings.set("backbone", out.timings.get("backbone") + elapsed_ms(t0));
  return p;
}

// lerobot's SinusoidalPositionalEncoding of an integer timestep, float32: [sin(t f_k), cos(t f_k)],
// f_k = exp(-k * (ln(10000) / half)).
void action_time_sinusoid(int64_t timestep, int64_t width, float* out) {
  const int64_t half = width / 2;
  const float c = float(std::log(10000.0)) / float(half);
  for (int64_t k = 0; k < half; ++k) {
    const float arg = float(timestep) * std::exp(-float(k) * c);
    out[k] = std::sin(arg);
    out[half + k] = std::cos(arg);
  }
}

void Gr00tN17::velocity(int64_t B, Ptr<const float> x, float time, Ptr<float> v) {
  backend::Backend& be = *be_;
  const int64_t H = head_.action_horizon, A = head_.max_action_dim, Din = head_.input_dim, T = H + 1;
  // The step index from the time (k / steps), and its bucket as upstream computes it: int((k / steps) * buckets).
  const int64_t k = std::llround(double(time) * double(head_.steps));
  const int64_t bucket = int64_t((double(k) / double(head_.steps)) * double(head_.buckets));
  const std::string step = dumping() ? "step" + std::to_string(k) : std::string();

  // Action encoder: W1(x), then [W1(x) | sinusoid(bucket)] -> W2 -> swish -> W3, plus the position table. The
  // sinusoid is one row, broadcast into every action row.
  be.linear(*act1_, x, B * H, act_in_.at(), false, 2 * Din);
  host_sinusoid_.resize(std::size_t(Din));
  action_time_sinusoid(bucket, Din, host_sinusoid_.data());
  be.upload(host_sinusoid_.data(), Din, act_mid_.at());
  be.copy_rows(act_mid_.at(), 0, act_in_.at(Din), 2 * Din, B * H, Din);
  be.linear(*act2_, act_in_.at(), B * H, act_mid_.at());
  be.activate(act_mid_.at(), B * H * Din, Activation::silu);
  // Tokens: the state token, then the encoded actions (with their positions), per item.
  for (int64_t b = 0; b < B; ++b) {
    be.linear(*act3_, act_mid_.at(b * H * Din), H, tokens_.at((b * T + 1) * Din), false, 0);
    if (dumping() && k == 0 && b == 0)
      dump_array<float>(be, "mid.action_encoder.step0", DType::f32, {1, H, Din}, tokens_.at(Din));
    if (head_.add_pos_embed) be.add(tokens_.at((b * T + 1) * Din), action_pos_.at(), H * Din, tokens_.at((b * T + 1) * Din));
    be.copy_rows(state_tok_.at(b * Din), Din, tokens_.at(b * T * Din), Din, 1, Din);
  }
  // DiT at this time, then the decoder; the velocity is the action rows.
  dit_.time_embedding(be, bucket, B, temb_.at());
  if (dumping()) dump_array<float>(be, "mid.temb." + step, DType::f32, {B, Din}, temb_.at());
  dit_.forward(be, tokens_.at(), B, T, temb_.at(), kv_, dit_masks_, dit_out_.at());
  if (dumping() && k == 0) dump_array<float>(be, "mid.dit_out.step0", DType::f32, {B, T, head_.hidden}, dit_out_.at());
  be.linear(*dec1_, dit_out_.at(), B * T, dec_mid_.at());
  be.activate(dec_mid_.at(), B * T * head_.hidden, Activation::relu);
  be.linear(*dec2_, dec_mid_.at(), B * T, dec_out_.at());
  if (dumping()) dump_array<float>(be, "mid.decoder_out." + step, DType::f32, {B, T, A}, dec_out_.at());
  for (int64_t b = 0; b < B; ++b) be.copy_rows(dec_out_.at((b * T + 1) * A), A, v + b * H * A, A, H, A);
}

ModelOutput Gr00tN17::predict(const std::vector<ModelInput>& batch) {
  ModelOutput out = begin_predict(batch);
  backend::Backend& be = *be_;
  const double flops_before = be.flops().total();
  const int64_t B = int64_t(batch.size()), D = head_.backbone_dim, Din = head_.input_dim;
  out.timings.set("preprocess", 0);

  // The backbone per observation, then one context of the longest prompt (shorter ones padded, the padding masked).
  std::vector<Prefix> prefixes;
  int64_t Lmax = 0;
  for (int64_t b = 0; b < B; ++b) {
    prefixes.push_back(encode_observation(batch[std::size_t(b)], b, out));
    Lmax = std::max(Lmax, prefixes.back().len);
  }
  const auto t0 = std::chrono::steady_clock::now();
  grow(be, context_, B * Lmax * D);
  const int64_t T = head_.action_horizon + 1;
  std::vector<uint8_t> text_keys(std::size_t(B * T * Lmax), 0), image_keys(text_keys.size(), 0), all_keys(text_keys.size(), 0);
  std::vector<float> zeros(std::size_t(Lmax * D), 0.f);
  for (int64_t b = 0; b < B; ++b) {
    const Prefix& p = prefixes[std::size_t(b)];
    be.upload(zeros.data(), Lmax * D, context_.at(b * Lmax * D));
    be.copy_rows(p.vl.at(), D, context_.at(b * Lmax * D), D, p.len, D);
    for (int64_t q = 0; q < T; ++q)
      for (int64_t j = 0; j < p.len; ++j) {
        const std::size_t at = std::size_t((b * T + q) * Lmax + j);
        image_keys[at] = p.image_mask[std::size_t(j)];
        text_keys[at] = !p.image_mask[std::size_t(j)];
        all_keys[at] = 1;
      }
  }
  for (auto* a : {&text_keys_, &image_keys_, &all_keys_})
    if (a->size() < B * T * Lmax) *a = be.alloc<uint8_t>(B * T * Lmax);
  be.upload(text_keys.data(), B * T * Lmax, text_keys_.at());
  be.upload(image_keys.data(), B * T * Lmax, image_keys_.at());
  be.upload(all_keys.data(), B * T * Lmax, all_keys_.at());
  dit_.project_context(be, context_.at(), B, Lmax, kv_);
  // Which keys each DiT block reads: text or image tokens alternately (AlternateVLDiT), else every real token.
  dit_masks_.clear();
  for (int64_t i = 0; i < dit_.layers(); ++i) {
    if (!dit_.cross(i)) dit_masks_.push_back(Ptr<const uint8_t>());
    else if (!head_.dit.alternate_vl) dit_masks_.push_back(all_keys_.at());
    else dit_masks_.push_back(i % (2 * head_.dit.attend_text_every_n_blocks) == 0 ? text_keys_.at() : image_keys_.at());
  }

  // The state token: the normalised state, zero-padded, through the embodiment's state encoder.
  const int64_t S = head_.max_state_dim;
  std::vector<float> state(std::size_t(B * S), 0.f);
  for (int64_t b = 0; b < B; ++b)
    std::copy(batch[std::size_t(b)].state.begin(), batch[std::size_t(b)].state.end(), state.begin() + b * S);
  if (dumping()) dump("pre.state", Tensor{DType::f32, {B, 1, S}, state.data(), nullptr});
  grow(be, state_, B * S);
  grow(be, state_mid_, B * head_.hidden);
  grow(be, state_tok_, B * Din);
  be.upload(state.data(), B * S, state_.at());
  be.linear(*state1_, state_.at(), B, state_mid_.at());
  be.activate(state_mid_.at(), B * head_.hidden, Activation::relu);
  be.linear(*state2_, state_mid_.at(), B, state_tok_.at());
  if (dumping()) dump_array<float>(be, "mid.state_features", DType::f32, {B, 1, Din}, state_tok_.at());
  out.timings.set("backbone", out.timings.get("backbone") + elapsed_ms(t0));

  // Euler from noise at t = 0 to actions at t = 1.
  const int64_t H = head_.action_horizon, A = head_.max_action_dim;
  grow(be, noise_x_, B * H * A);
  grow(be, noise_v_, B * H * A);
  // The denoise loop's buffers, sized before it so that no step allocates.
  grow(be, act_in_, B * H * 2 * Din);
  grow(be, act_mid_, B * H * Din);
  grow(be, tokens_, B * (H + 1) * Din);
  grow(be, temb_, B * Din);
  grow(be, dit_out_, B * (H + 1) * head_.hidden);
  grow(be, dec_mid_, B * (H + 1) * head_.hidden);
  grow(be, dec_out_, B * (H + 1) * A);
  const Schedule schedule{0.0, 1.0, head_.steps};
  sample_actions(
      be, batch, noise_x_.at(), noise_v_.at(), schedule,
      [&](Ptr<const float> x, float time, Ptr<float> v) { velocity(B, x, time, v); },
      [&](Ptr<const float> v) {
        if (dumping()) dump_array<float>(be, "mid.velocity.step0", DType::f32, {B, H, A}, v);
      },
      out);
  if (dumping()) dump_array<float>(be, "out.action_pred", DType::f32, {B, H, A}, noise_x_.at());
  out.flops = be.flops().total() - flops_before;
  return out;
}

}  // namespace

std::unique_ptr<Model> load_gr00t_n17(const fs::path& dir, const Json& config, TensorStore weights,
                                      const LoadOptions& options) {
  return std::make_unique<Gr00tN17>(dir, config, std::move(weights), options);
}

}  // namespace tether::models
