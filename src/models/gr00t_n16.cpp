// GR00T N1.6 (Isaac-GR00T's Gr00tN1d6; see gr00t.h): the Eagle backbone per observation (SigLIP2 per camera frame,
// pixel unshuffle and the mlp1 projector, the image rows spliced into the prompt's <IMG_CONTEXT> tokens, Qwen3 cut at
// select_layer with its final norm), then the action head shared with N1.7 (gr00t_head.h) without VL self-attention.
// The state is encoded here, per group as the checkpoint's processor says (sin/cos, mean/std or min/max).
// docs/design/gr00t.md section 5 says what upstream computes and where.
#include <algorithm>
#include <chrono>
#include <cmath>

#include "core/error.h"
#include "models/backbone.h"
#include "models/blocks/decoder.h"
#include "models/blocks/linear.h"
#include "models/blocks/vision_tower.h"
#include "models/gr00t.h"
#include "models/gr00t_head.h"
#include "text/tokenizer.h"
#include "vision/gr00t_preprocess.h"

namespace tether::models {

namespace fs = std::filesystem;
using backend::Ptr;

namespace {

constexpr const char* kVision = "backbone.model.vision_model.vision_model.";
constexpr const char* kProjector = "backbone.model.mlp1.";
constexpr const char* kText = "backbone.model.language_model.model.";

// How one state group reaches the state encoder (Isaac-GR00T's StateActionProcessor.apply_state).
struct StateGroup {
  enum class Kind { min_max, sin_cos, mean_std } kind = Kind::min_max;
  int64_t dim = 0;                   // raw values
  std::vector<double> a, b;          // min / max, or mean / std
};

class Gr00tN16 final : public Gr00tModel {
 public:
  Gr00tN16(const fs::path& dir, const Json& config, TensorStore store, const LoadOptions& options);

 private:
  Backbone encode_backbone(const ModelInput& in, int64_t item, ModelOutput& out) override;
  void head_state(const ModelInput& in, float* out) const override;
  void add_state_encoding(const fs::path& dir, const Gr00tEmbodiment& e) override;

  vision::Gr00tImageGeometry geometry_;
  bool formalize_ = true, clip_outliers_ = true;
  std::vector<std::vector<StateGroup>> state_encodings_;  // per embodiment slot
  std::unique_ptr<text::PretrainedTokenizer> tokenizer_;
  int32_t image_token_ = 0;

  VisionTower vision_;
  backend::Array<float> proj_ln_w_, proj_ln_b_;  // mlp1.0, its 4C entries in the order project() writes them
  std::unique_ptr<backend::LinearWeights> proj_fc1_, proj_fc2_;
  DecoderConfig text_cfg_;
  DecoderStack text_;
  std::unique_ptr<backend::Table> embed_;
  backend::Array<float> final_norm_;

  // Per-request buffers, grown once per shape.
  backend::Array<float> pixels_, patches_, unshuffled_, proj_mid_, image_rows_, x_, features_;
  backend::Array<int64_t> ids_, positions_;
  backend::Array<uint8_t> causal_;
};

std::vector<std::string> key_list(const Json& modality, const char* field) {
  std::vector<std::string> out;
  const Json v = modality.value(field, Json(nullptr));
  if (v.is_array())
    for (const auto& k : v) out.push_back(k.get<std::string>());
  return out;
}

// StateActionProcessor's statistics of one state group: min/max (or q01/q99), mean/std.
std::vector<double> stat_values(const Json& stats, const std::string& key, const char* name, int64_t dim,
                                const std::string& where) {
  if (!stats.contains(key) || !stats.at(key).contains(name) || !stats.at(key).at(name).is_array())
    throw Error(ErrorCode::format, where + ": no " + name + " for state '" + key + "'");
  auto v = stats.at(key).at(name).get<std::vector<double>>();
  if (int64_t(v.size()) != dim)
    throw Error(ErrorCode::format, where + ": state '" + key + "' " + name + " has " + std::to_string(v.size()) +
                                       " values, expected " + std::to_string(dim));
  return v;
}

Gr00tN16::Gr00tN16(const fs::path& dir, const Json& config, TensorStore store, const LoadOptions& options)
    : Gr00tModel(options) {
  const std::string where = (dir / "config.json").string();
  backend::Backend& be = *be_;
  const cpu::Precision precision = options.precision;
  head_ = Gr00tHeadConfig::from_json(config, where, "nvidia/Eagle-Block2A-2B-v2");
  if (head_.vl_layers != 0) throw Error(ErrorCode::format, where + ": N1.6 has no VL self-attention");
  read_gr00t_embodiment(dir, options.embodiment);  // its errors before the backbone loads
  const Json kwargs = gr00t_processor_kwargs(dir);
  const std::string pwhere = gr00t_sidecar(dir, "processor_config.json").string();
  geometry_ = vision::Gr00tImageGeometry::from_n16_processor_kwargs(kwargs, pwhere);
  formalize_ = json_get_or<bool>(kwargs, "formalize_language", true, pwhere);
  clip_outliers_ = json_get_or<bool>(kwargs, "clip_outliers", true, pwhere);

  // The Eagle directory the config names (Isaac-GR00T vendors it; Tether looks beside the checkpoint, then in the
  // hub cache): its architecture and tokenizer.
  fs::path bdir;
  try {
    bdir = find_backbone_dir(dir, head_.model_name, "model_name in config.json");
  } catch (const Error& e) {
    throw Error(e.code(), std::string(e.what()) + "; the Eagle directory is not a hub repository: copy Isaac-GR00T's "
                          "gr00t/model/modules/nvidia/Eagle-Block2A-2B-v2 to " + (dir / head_.model_name).string());
  }
  const std::string bwhere = (bdir / "config.json").string();
  const Json bcfg = read_json_file(bwhere);
  if (json_get_or<int64_t>(bcfg, "select_layer", -1, bwhere) != -1)
    throw Error(ErrorCode::unsupported, bwhere + ": only the vision tower's last layer (select_layer -1) is supported");
  if (json_get_or<double>(bcfg, "downsample_ratio", 0.5, bwhere) != 0.5)
    throw Error(ErrorCode::unsupported, bwhere + ": only downsample_ratio 0.5 (a 2x2 pixel unshuffle) is supported");
  const Json vision_json = bcfg.value("vision_config", Json::object());
  if (json_get_or<bool>(vision_json, "use_rope", false, bwhere) ||
      json_get_or<bool>(vision_json, "use_windows_attn", false, bwhere))
    throw Error(ErrorCode::unsupported, bwhere + ": SigLIP2 with RoPE or windowed attention is not supported");
  const VisionConfig vcfg = VisionConfig::from_siglip2_json(vision_json, bwhere + ": vision_config");
  text_cfg_ = DecoderConfig::from_llama_json(bcfg.value("text_config", Json::object()), bwhere + ": text_config");
  text_cfg_.qk_norm = true;
  text_cfg_.rope_wavelength = json_get_or<float>(bcfg.value("text_config", Json::object()), "rope_theta", 1000000.0f,
                                                 bwhere);
  if (head_.select_layer < 1 || head_.select_layer > text_cfg_.layers)
    throw Error(ErrorCode::format, where + ": select_layer " + std::to_string(head_.select_layer) + " is outside the " +
                                       std::to_string(text_cfg_.layers) + " text layers");
  if (text_cfg_.hidden != head_.backbone_dim)
    throw Error(ErrorCode::format, where + ": backbone_embedding_dim is not the text model's width");
  // Eagle3_VLConfig's code default (151667) is another token; only the directory's config.json is trusted.
  image_token_ = json_get<int32_t>(bcfg, "image_token_index", bwhere);
  tokenizer_ = std::make_unique<text::PretrainedTokenizer>(text::load_pretrained_tokenizer(bdir.string()));
  for (const char* token : {"<|im_start|>", "<|im_end|>", "<img>", "</img>"})
    if (!tokenizer_->tokenizer.token_to_id(token))
      throw Error(ErrorCode::format, tokenizer_->source + ": no token " + token);
  if (tokenizer_->tokenizer.token_to_id("<IMG_CONTEXT>") != image_token_)
    throw Error(ErrorCode::format, tokenizer_->source + ": <IMG_CONTEXT> is not image_token_index of " + bwhere);

  weights_ = std::make_unique<Weights>(std::move(store));
  Weights& w = *weights_;
  vision_.load(be, w, kVision, vcfg, precision);
  // mlp1 reads the 2x2 unshuffle, channel c * 4 + k (k = dy * 2 + dx). project() writes k * C + c instead (each
  // sub-pixel's row copied whole), so the LayerNorm's affine and fc1's input columns are permuted to match.
  const int64_t C = vcfg.hidden, C4 = 4 * C, Dt = text_cfg_.hidden;
  auto permuted = [&](const float* v, int64_t rows) {
    std::vector<float> out(std::size_t(rows * C4));
    for (int64_t r = 0; r < rows; ++r)
      for (int64_t c = 0; c < C; ++c)
        for (int64_t k = 0; k < 4; ++k) out[std::size_t(r * C4 + k * C + c)] = v[r * C4 + c * 4 + k];
    return out;
  };
  const std::vector<float> ln_w = permuted(w.f32(std::string(kProjector) + "0.weight", {C4}), 1),
                           ln_b = permuted(w.f32(std::string(kProjector) + "0.bias", {C4}), 1),
                           fc1 = permuted(w.f32(std::string(kProjector) + "1.weight", {Dt, C4}), Dt);
  proj_ln_w_ = be.alloc<float>(C4);
  proj_ln_b_ = be.alloc<float>(C4);
  be.upload(ln_w.data(), C4, proj_ln_w_.at());
  be.upload(ln_b.data(), C4, proj_ln_b_.at());
  proj_fc1_ = be.pack_linear(fc1.data(), Dt, C4, w.f32(std::string(kProjector) + "1.bias", {Dt}), precision);
  proj_fc2_ = load_linear(be, w, std::string(kProjector) + "3", Dt, Dt, true, precision);
  embed_ = be.table(w.raw(std::string(kText) + "embed_tokens.weight", {text_cfg_.vocab, Dt}));
  text_.load(be, w, std::string(kText) + "layers.", text_cfg_, head_.select_layer, precision, false);
  final_norm_ = be.constant(w.f32(std::string(kText) + "norm.weight", {Dt}), Dt);
  load_head(w, precision);
  fill_spec(gr00t_n16_family(), tokenizer_->source, geometry_.resize_edge(), geometry_.resize_edge(), precision,
            w.stored_dtype(), where);
  add_embodiment(dir, options.embodiment, w);
  w.finish_loading();
}

void Gr00tN16::add_state_encoding(const fs::path& dir, const Gr00tEmbodiment& e) {
  // The state groups' encodings and statistics, in modality order.
  const Json kwargs = gr00t_processor_kwargs(dir);
  const std::string pwhere = gr00t_sidecar(dir, "processor_config.json").string();
  const bool sin_cos = json_get_or<bool>(kwargs, "apply_sincos_state_encoding", false, pwhere);
  const bool percentiles = json_get_or<bool>(kwargs, "use_percentiles", false, pwhere);
  const Json modality = kwargs.at("modality_configs").at(e.tag).value("state", Json::object());
  const std::vector<std::string> sin_cos_keys = key_list(modality, "sin_cos_embedding_keys"),
                                  mean_std_keys = key_list(modality, "mean_std_embedding_keys");
  const fs::path stats_path = gr00t_sidecar(dir, "statistics.json");
  const Json stats = read_json_file(stats_path.string()).at(e.tag).at("state");
  std::vector<StateGroup> groups;
  int64_t encoded = 0;
  for (const auto& g : e.state_groups) {
    StateGroup s;
    s.dim = g.dim;
    auto listed = [&](const std::vector<std::string>& keys) {
      return std::find(keys.begin(), keys.end(), g.name) != keys.end();
    };
    if (sin_cos && listed(sin_cos_keys)) {
      s.kind = StateGroup::Kind::sin_cos;
    } else if (listed(mean_std_keys)) {
      s.kind = StateGroup::Kind::mean_std;
      s.a = stat_values(stats, g.name, "mean", g.dim, stats_path.string());
      s.b = stat_values(stats, g.name, "std", g.dim, stats_path.string());
    } else {
      s.a = stat_values(stats, g.name, percentiles ? "q01" : "min", g.dim, stats_path.string());
      s.b = stat_values(stats, g.name, percentiles ? "q99" : "max", g.dim, stats_path.string());
    }
    encoded += s.kind == StateGroup::Kind::sin_cos ? 2 * s.dim : s.dim;
    groups.push_back(std::move(s));
  }
  if (encoded > head_.max_state_dim)
    throw Error(ErrorCode::format, pwhere + ": embodiment '" + e.tag + "' encodes its state into " +
                                       std::to_string(encoded) + " values, more than max_state_dim " +
                                       std::to_string(head_.max_state_dim));
  state_encodings_.push_back(std::move(groups));
}

void Gr00tN16::head_state(const ModelInput& in, float* out) const {
  // numpy's arithmetic: float32 state, float64 statistics, each result stored back to float32.
  int64_t raw = 0, at = 0;
  for (const StateGroup& g : state_encodings_.at(active_slot())) {
    const float* x = in.state.data() + raw;
    switch (g.kind) {
      case StateGroup::Kind::sin_cos:
        for (int64_t j = 0; j < g.dim; ++j) out[at + j] = std::sin(x[j]);
        for (int64_t j = 0; j < g.dim; ++j) out[at + g.dim + j] = std::cos(x[j]);
        at += 2 * g.dim;
        break;
      case StateGroup::Kind::mean_std:
        for (int64_t j = 0; j < g.dim; ++j)
          out[at + j] = g.b[j] != 0 ? float((double(x[j]) - g.a[j]) / g.b[j]) : x[j];
        at += g.dim;
        break;
      case StateGroup::Kind::min_max:
        for (int64_t j = 0; j < g.dim; ++j) {
          const double lo = g.a[j], hi = g.b[j];
          float v = 0.0f;
          if (!(std::fabs(hi - lo) <= 1e-8 + 1e-5 * std::fabs(lo))) {  // np.isclose(max, min) -> 0
            v = float((double(x[j]) - lo) / (hi - lo));
            v = 2.0f * v - 1.0f;
          }
          if (clip_outliers_) v = std::clamp(v, -1.0f, 1.0f);
          out[at + j] = v;
        }
        at += g.dim;
        break;
    }
    raw += g.dim;
  }
}

Gr00tModel::Backbone Gr00tN16::encode_backbone(const ModelInput& in, int64_t item, ModelOutput& out) {
  backend::Backend& be = *be_;
  auto t0 = std::chrono::steady_clock::now();
  // Frames: every camera of the embodiment, in its order; each keeps its own size (the tower runs per image).
  std::vector<vision::EagleFrame> frames;
  for (const std::string& cam : spec().cameras) {
    auto it = in.images.find(cam);
    if (it == in.images.end())
      throw Error(ErrorCode::invalid_argument, "observation " + std::to_string(item) + ": no image for camera '" + cam +
                                                   "' (GR00T needs every camera of its embodiment)");
    frames.push_back(vision::eagle_preprocess_frame(it->second, geometry_));
  }
  std::vector<int64_t> image_tokens;
  for (const auto& f : frames) image_tokens.push_back(gr00t_n16_image_tokens(f.image.height, f.image.width));
  const std::string prompt = gr00t_n16_prompt(gr00t_formalize_language(in.instruction, formalize_), image_tokens);
  const std::vector<int32_t> ids = tokenizer_->tokenizer.encode(prompt, false);
  const int64_t L = int64_t(ids.size()), D = text_cfg_.hidden;
  if (dumping()) {
    std::vector<int64_t> ids64(ids.begin(), ids.end());
    dump("pre.input_ids", Tensor{DType::i64, {1, L}, ids64.data(), nullptr});
  }
  out.timings.set("preprocess", out.timings.get("preprocess") + elapsed_ms(t0));

  // Vision: SigLIP2 per frame, the 2x2 unshuffle as whole-row copies, then mlp1 (LayerNorm, fc1, exact GELU, fc2).
  t0 = std::chrono::steady_clock::now();
  const int64_t C = vision_.hidden(), C4 = 4 * C, P = 14;
  int64_t rows_total = 0;
  for (const auto& f : frames) rows_total += gr00t_n16_image_tokens(f.image.height, f.image.width);
  grow(be, image_rows_, rows_total * D);
  int64_t row = 0;
  for (std::size_t k = 0; k < frames.size(); ++k) {
    const auto& f = frames[k];
    const int64_t H = f.image.height, W = f.image.width, gh = H / P, gw = W / P, n = gh * gw, m = n / 4;
    grow(be, pixels_, 3 * H * W);
    be.upload(f.pixels.data(), 3 * H * W, pixels_.at());
    grow(be, patches_, n * C);
    vision_.forward(be, pixels_.at(), 1, H, W, patches_.at());
    if (dumping()) dump_array<float>(be, "mid.vision." + spec().cameras[k], DType::f32, {1, n, C}, patches_.at());
    grow(be, unshuffled_, m * std::max(C4, D));
    for (int64_t y = 0; y < gh / 2; ++y)
      for (int64_t dy = 0; dy < 2; ++dy)
        for (int64_t dx = 0; dx < 2; ++dx)
          be.copy_rows(patches_.at(((2 * y + dy) * gw + dx) * C), 2 * C, unshuffled_.at(y * (gw / 2) * C4 + (dy * 2 + dx) * C),
                       C4, gw / 2, C);
    grow(be, proj_mid_, m * C4);
    be.layer_norm(unshuffled_.at(), m, C4, proj_ln_w_.at(), proj_ln_b_.at(), 1e-5f, proj_mid_.at());
    be.linear(*proj_fc1_, proj_mid_.at(), m, unshuffled_.at());
    be.activate(unshuffled_.at(), m * D, backend::Activation::gelu_erf);
    be.linear(*proj_fc2_, unshuffled_.at(), m, image_rows_.at(row * D));
    if (dumping()) dump_array<float>(be, "mid.projector." + spec().cameras[k], DType::f32, {m, D}, image_rows_.at(row * D));
    row += m;
  }
  be.synchronize();  // a GPU runs behind the host: time the work, not its queueing
  out.timings.set("vision", out.timings.get("vision") + elapsed_ms(t0));

  // Text: token embeddings with the image rows at the <IMG_CONTEXT> tokens (in order), Qwen3 cut at select_layer,
  // then its final norm: N1.6's feature is the normed last hidden state.
  t0 = std::chrono::steady_clock::now();
  grow(be, x_, L * D);
  grow(be, features_, L * D);
  if (positions_.size() < L) positions_ = be.alloc<int64_t>(L);
  Backbone b;
  embed_prompt(*embed_, ids, image_token_, image_rows_.at(), rows_total, D, item, ids_, x_.at(), b);
  if (dumping()) dump_array<float>(be, "mid.inputs_embeds", DType::f32, {1, L, D}, x_.at());
  std::vector<int64_t> positions(static_cast<std::size_t>(L));
  for (int64_t i = 0; i < L; ++i) positions[std::size_t(i)] = i;
  be.upload(positions.data(), L, positions_.at());
  upload_causal_mask(L, causal_);
  KvCache cache;
  cache.resize(be, text_.layers(), 1, L, text_cfg_.kv_heads * text_cfg_.head_dim);
  text_.forward(be, x_.at(), 1, L, positions_.at(), causal_.at(), cache);
  be.rms_norm(x_.at(), L, D, final_norm_.at(), text_cfg_.rms_norm_eps, features_.at());
  if (dumping()) dump_array<float>(be, "mid.backbone_features", DType::f32, {1, L, D}, features_.at());
  be.synchronize();  // a GPU runs behind the host: time the work, not its queueing
  out.timings.set("backbone", out.timings.get("backbone") + elapsed_ms(t0));
  b.features = features_.at();
  return b;
}

}  // namespace

int64_t gr00t_n16_image_tokens(int64_t height, int64_t width) { return (height / 28) * (width / 28); }

std::string gr00t_n16_prompt(const std::string& language, const std::vector<int64_t>& image_tokens) {
  std::string prompt = "<|im_start|>system\nYou are a helpful assistant.<|im_end|>\n<|im_start|>user\n" + language;
  for (std::size_t k = 0; k < image_tokens.size(); ++k) {
    prompt += "<image " + std::to_string(k + 1) + "><img>";
    for (int64_t t = 0; t < image_tokens[k]; ++t) prompt += "<IMG_CONTEXT>";
    prompt += "</img>";
  }
  return prompt + "<|im_end|>\n";
}

std::unique_ptr<Model> load_gr00t_n16(const fs::path& dir, const Json& config, TensorStore weights,
                                      const LoadOptions& options) {
  return load_gr00t_embodiment(dir, config, std::move(weights), options, [&](TensorStore store) {
    return std::make_unique<Gr00tN16>(dir, config, std::move(store), options);
  });
}

}  // namespace tether::models
