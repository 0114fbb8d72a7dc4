#include "models/smolvla.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <optional>

#include "backend/cpu/gemm.h"
#include "backend/cpu/kernels.h"
#include "models/backbone.h"
#include "models/flow_matching.h"
#include "models/llama_decoder.h"
#include "models/siglip.h"
#include "text/tokenizer.h"
#include "vision/preprocess.h"

namespace tether::models {

namespace fs = std::filesystem;
using namespace tether::cpu;

namespace {

// lerobot's apply_rope uses a fixed wavelength, whatever rope_theta the VLM config says.
constexpr float kRopeWavelength = 10000.0f;

double ms_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
}

// lerobot's get_intermediate_size for the action expert's MLP width.
int64_t expert_intermediate_size(int64_t hidden) {
  int64_t h = int64_t(2 * hidden / 3);
  h = 4 * h;
  return 256 * ((h + 255) / 256);
}

struct TokenizerSettings {
  int max_length = 48;
  std::string padding = "longest";
  bool pad_right = true, truncation = true, append_newline = true;
};

// Reads the tokenizer step of policy_preprocessor.json (padding, max length, side) when present.
TokenizerSettings read_tokenizer_settings(const fs::path& dir, const Json& config) {
  TokenizerSettings s;
  const std::string where = (dir / "config.json").string();
  s.max_length = json_get_or<int>(config, "tokenizer_max_length", 48, where);
  s.padding = json_get_or<std::string>(config, "pad_language_to", "longest", where);
  const fs::path pre = dir / "policy_preprocessor.json";
  if (!fs::exists(pre)) return s;
  const Json p = read_json_file(pre.string());
  s.append_newline = false;
  for (const auto& step : p.value("steps", Json::array())) {
    const std::string name = step.value("registry_name", "");
    if (name == "smolvla_new_line_processor") s.append_newline = true;
    if (name == "tokenizer_processor") {
      const Json& c = step.value("config", Json::object());
      s.max_length = json_get_or<int>(c, "max_length", s.max_length, pre.string());
      s.padding = json_get_or<std::string>(c, "padding", s.padding, pre.string());
      s.truncation = json_get_or<bool>(c, "truncation", true, pre.string());
      s.pad_right = json_get_or<std::string>(c, "padding_side", "right", pre.string()) == "right";
    }
  }
  return s;
}

class SmolVLA final : public Model {
 public:
  SmolVLA(const fs::path& dir, const Json& config, TensorStore weights, const LoadOptions& options);
  const ModelSpec& spec() const override { return spec_; }
  ModelOutput predict(const std::vector<ModelInput>& batch) override;

 private:
  void build_prefix(const std::vector<ModelInput>& batch, ModelOutput& out);
  void run_prefix();
  void denoise_step(const float* x, float time, float* v);
  void ensure_buffers(int64_t batch, int64_t prefix_len);

  ModelSpec spec_;
  TokenizerSettings tok_settings_;
  std::optional<text::PretrainedTokenizer> tokenizer_;  // set in the constructor (no empty state)
  int64_t empty_cameras_ = 0, prefix_length_ = -1, self_attn_every_ = 2;
  bool cross_mode_ = true;
  double min_period_ = 4e-3, max_period_ = 4.0;

  std::unique_ptr<Weights> weights_;
  LlamaConfig text_cfg_;
  VisionTower vision_;
  PixelShuffleConnector connector_;
  Tensor embed_tokens_;  // stored dtype, rows converted on lookup (only the used rows are ever read)
  std::vector<LlamaLayer> vlm_;
  std::vector<LlamaLayer> expert_;
  std::vector<int> expert_at_;  // VLM layer index -> expert layer index or -1
  int64_t expert_hidden_ = 0;
  const float *expert_norm_ = nullptr, *vlm_norm_ = nullptr;
  cpu::PackedLinear state_proj_, action_in_, action_out_, time_in_, time_out_;

  // Per-request state, sized once per (batch, prefix length) so the denoise loop never allocates.
  int64_t B_ = 0, Lp_ = 0;
  std::vector<float> pixels_, vision_out_, img_tokens_, prefix_x_, q_, qkv_, attn_, scratch_;
  std::vector<uint8_t> prefix_pad_, prefix_mask_, self_mask_, cross_mask_, img_present_;
  std::vector<int8_t> prefix_att_;
  std::vector<int64_t> prefix_pos_, suffix_pos_, cross_pos_;
  std::vector<std::vector<float>> k_cache_, v_cache_;        // per VLM layer [B, Lp + chunk, kv_dim]
  std::vector<std::vector<float>> cross_k_, cross_v_;        // per VLM layer [B, Lp, kv_dim] (cross layers)
  std::vector<float> x_t_, v_t_, suffix_x_, cat_, time_emb_, mlp_h_, normed_;
};

SmolVLA::SmolVLA(const fs::path& dir, const Json& config, TensorStore weights, const LoadOptions& options) {
  const cpu::Precision precision = options.precision;
  spec_.precision = precision;
  const std::string where = (dir / "config.json").string();
  const FamilyDescriptor& family = smolvla_family();
  spec_.family = family.name;
  spec_.stages = family.stages;
  spec_.missing_camera_rule = family.missing_camera_rule;
  spec_.tokenizer = tokenizer_kind_name(family.tokenizer);
  spec_.camera_prefix = "observation.images.";
  spec_.state_key = "observation.state";
  spec_.action_key = "action";
  if (json_get_or<bool>(config, "adapt_to_pi_aloha", false, where))
    throw Error(ErrorCode::unsupported, where + ": adapt_to_pi_aloha is not supported yet");
  if (json_get_or<bool>(config, "add_image_special_tokens", false, where))
    throw Error(ErrorCode::unsupported, where + ": add_image_special_tokens is not supported yet");

  // Features: camera order is the order of VISUAL entries in input_features, as upstream iterates them.
  const Json& inputs = json_get<Json>(config, "input_features", where);
  for (auto it = inputs.begin(); it != inputs.end(); ++it) {
    const std::string type = json_get<std::string>(*it, "type", where + ": input_features." + it.key());
    const auto shape = json_get<std::vector<int64_t>>(*it, "shape", where + ": input_features." + it.key());
    if (type == "VISUAL") spec_.cameras.push_back(it.key());
    if (type == "STATE") {
      spec_.state_key = it.key();
      spec_.state_dim = shape.at(0);
    }
  }
  empty_cameras_ = json_get_or<int64_t>(config, "empty_cameras", 0, where);
  for (int64_t i = 0; i < empty_cameras_; ++i) {
    spec_.cameras.push_back("observation.images.empty_camera_" + std::to_string(i));
    spec_.synthetic_cameras.push_back(spec_.cameras.back());
  }
  const Json& outputs = json_get<Json>(config, "output_features", where);
  for (auto it = outputs.begin(); it != outputs.end(); ++it) {
    if (json_get<std::string>(*it, "type", where) == "ACTION") {
      spec_.action_key = it.key();
      spec_.action_dim = json_get<std::vector<int64_t>>(*it, "shape", where).at(0);
    }
  }
  if (spec_.cameras.empty()) throw Error(ErrorCode::format, where + ": input_features has no VISUAL feature");
  if (spec_.action_dim == 0) throw Error(ErrorCode::format, where + ": output_features has no ACTION feature");

  spec_.chunk_size = json_get_or<int64_t>(config, "chunk_size", 50, where);
  spec_.num_steps = json_get_or<int64_t>(config, "num_steps", 10, where);
  spec_.max_state_dim = json_get_or<int64_t>(config, "max_state_dim", 32, where);
  spec_.max_action_dim = json_get_or<int64_t>(config, "max_action_dim", 32, where);
  if (spec_.state_dim > spec_.max_state_dim || spec_.action_dim > spec_.max_action_dim)
    throw Error(ErrorCode::format, where + ": state/action dims exceed max_state_dim/max_action_dim");
  prefix_length_ = json_get_or<int64_t>(config, "prefix_length", -1, where);
  self_attn_every_ = json_get_or<int64_t>(config, "self_attn_every_n_layers", 2, where);
  cross_mode_ = json_get_or<std::string>(config, "attention_mode", "cross_attn", where).find("cross") != std::string::npos;
  min_period_ = json_get_or<double>(config, "min_period", 4e-3, where);
  max_period_ = json_get_or<double>(config, "max_period", 4.0, where);
  tok_settings_ = read_tokenizer_settings(dir, config);

  // VLM backbone: architecture and tokenizer come from the backbone's own files.
  const fs::path vlm_dir = find_backbone_dir(dir, json_get<std::string>(config, "vlm_model_name", where));
  const std::string vlm_where = (vlm_dir / "config.json").string();
  const Json vlm_cfg = read_json_file(vlm_where);
  const VisionConfig vision_cfg = VisionConfig::from_json(vlm_cfg.value("vision_config", Json::object()), vlm_where);
  text_cfg_ = LlamaConfig::from_json(json_get<Json>(vlm_cfg, "text_config", vlm_where), vlm_where);
  if (text_cfg_.rms_norm_eps == 1e-6f && !vlm_cfg["text_config"].contains("rms_norm_eps"))
    text_cfg_.rms_norm_eps = 1e-5f;  // SmolVLMConfig's default text config overrides Llama's eps
  const int64_t scale_factor = json_get_or<int64_t>(vlm_cfg, "scale_factor", 2, vlm_where);
  // Loaded as transformers' AutoTokenizer builds it (tokenizer class overrides, truncation side, pad token).
  tokenizer_.emplace(text::load_pretrained_tokenizer(vlm_dir.string()));

  auto resize = config.find("resize_imgs_with_padding");
  if (resize != config.end() && !resize->is_null()) {
    const auto wh = resize->get<std::vector<int64_t>>();
    spec_.image_width = wh.at(0);
    spec_.image_height = wh.at(1);
  }

  const int64_t num_vlm_layers = json_get_or<int64_t>(config, "num_vlm_layers", -1, where);
  const int64_t vlm_layers = num_vlm_layers > 0 ? std::min(num_vlm_layers, text_cfg_.layers) : text_cfg_.layers;
  const int64_t num_expert_layers = json_get_or<int64_t>(config, "num_expert_layers", -1, where);
  const int64_t expert_layers = num_expert_layers > 0 ? num_expert_layers : vlm_layers;
  if (vlm_layers % expert_layers != 0)
    throw Error(ErrorCode::format, where + ": num_vlm_layers is not a multiple of num_expert_layers");
  const double width_mult = json_get_or<double>(config, "expert_width_multiplier", 0.75, where);
  expert_hidden_ = int64_t(double(text_cfg_.hidden) * width_mult);

  // Weights.
  weights_ = std::make_unique<Weights>(std::move(weights));
  Weights& w = *weights_;
  const std::string vlm_prefix = "model.vlm_with_expert.vlm.model.";
  const std::string expert_prefix = "model.vlm_with_expert.lm_expert.";
  const int64_t D = text_cfg_.hidden, E = expert_hidden_, A = spec_.max_action_dim;
  vision_.load(w, vlm_prefix + "vision_model.", vision_cfg, precision);
  connector_.load(w, vlm_prefix + "connector.", vision_cfg.hidden, scale_factor, D, precision);
  embed_tokens_ = w.raw(vlm_prefix + "text_model.embed_tokens.weight", {text_cfg_.vocab, D});
  vlm_norm_ = w.f32(vlm_prefix + "text_model.norm.weight", {D});
  vlm_.resize(std::size_t(vlm_layers));
  for (int64_t i = 0; i < vlm_layers; ++i)
    vlm_[i].load(w, vlm_prefix + "text_model.layers." + std::to_string(i) + ".", text_cfg_, D,
                 text_cfg_.intermediate, D, /*cross=*/false, precision, /*kv_only=*/i + 1 == vlm_layers);
  const int64_t kv_dim = text_cfg_.kv_heads * text_cfg_.head_dim;
  expert_.resize(std::size_t(expert_layers));
  for (int64_t e = 0; e < expert_layers; ++e) {
    // Upstream reshapes k/v to read the VLM's K/V by *expert* index; routing below is by VLM index.
    const bool cross_shaped = cross_mode_ && !(self_attn_every_ > 0 && e % self_attn_every_ == 0);
    expert_[e].load(w, expert_prefix + "layers." + std::to_string(e) + ".", text_cfg_, E,
                     expert_intermediate_size(E), cross_shaped ? kv_dim : E, cross_shaped, precision);
  }
  expert_norm_ = w.f32(expert_prefix + "norm.weight", {E});
  const int64_t multiple = vlm_layers / expert_layers;
  expert_at_.assign(std::size_t(vlm_layers), -1);
  for (int64_t i = 0; i < vlm_layers; ++i) {
    if (multiple > 1 && i % multiple != 0) continue;
    expert_at_[i] = int(i / multiple);
    const bool self_route = !cross_mode_ || (self_attn_every_ > 0 && i % self_attn_every_ == 0);
    if (self_route == expert_[expert_at_[i]].cross)
      throw Error(ErrorCode::unsupported,
                  where + ": this num_expert_layers/self_attn_every_n_layers combination routes expert layer " +
                      std::to_string(expert_at_[i]) + " through the wrong attention kind (upstream fails too)");
  }
  pack_linear(w, state_proj_, "model.state_proj", D, spec_.max_state_dim, true, precision);
  pack_linear(w, action_in_, "model.action_in_proj", E, A, true, precision);
  pack_linear(w, action_out_, "model.action_out_proj", A, E, true, precision);
  pack_linear(w, time_in_, "model.action_time_mlp_in", E, 2 * E, true, precision);
  pack_linear(w, time_out_, "model.action_time_mlp_out", E, E, true, precision);
  spec_.weights_dtype = w.stored_dtype();
  w.finish_loading();
  if (spec_.image_height == 0) spec_.image_height = spec_.image_width = vision_cfg.image_size;
}

void SmolVLA::ensure_buffers(int64_t batch, int64_t prefix_len) {
  if (batch == B_ && prefix_len == Lp_) return;
  B_ = batch;
  Lp_ = prefix_len;
  const int64_t D = text_cfg_.hidden, E = expert_hidden_, C = spec_.chunk_size, A = spec_.max_action_dim;
  const int64_t q_dim = text_cfg_.heads * text_cfg_.head_dim, kv_dim = text_cfg_.kv_heads * text_cfg_.head_dim;
  const int64_t rows = std::max(B_ * Lp_, B_ * C);
  prefix_x_.assign(std::size_t(B_ * Lp_ * D), 0.f);
  q_.resize(std::size_t(rows * q_dim));
  qkv_.resize(std::size_t(rows * (q_dim + 2 * kv_dim)));
  attn_.resize(std::size_t(rows * q_dim));
  normed_.resize(std::size_t(rows * std::max(D, E)));
  k_cache_.assign(vlm_.size(), std::vector<float>(std::size_t(B_ * (Lp_ + C) * kv_dim)));
  v_cache_.assign(vlm_.size(), std::vector<float>(std::size_t(B_ * (Lp_ + C) * kv_dim)));
  cross_k_.assign(vlm_.size(), {});
  cross_v_.assign(vlm_.size(), {});
  for (std::size_t i = 0; i < vlm_.size(); ++i) {
    if (expert_at_[i] >= 0 && expert_[expert_at_[i]].cross) {
      cross_k_[i].resize(std::size_t(B_ * Lp_ * kv_dim));
      cross_v_[i].resize(std::size_t(B_ * Lp_ * kv_dim));
    }
  }
  prefix_pad_.assign(std::size_t(B_ * Lp_), 0);
  prefix_att_.assign(std::size_t(B_ * Lp_), 0);
  prefix_pos_.assign(std::size_t(B_ * Lp_), 0);
  prefix_mask_.assign(std::size_t(B_ * Lp_ * Lp_), 0);
  self_mask_.assign(std::size_t(B_ * C * (Lp_ + C)), 0);
  cross_mask_.assign(std::size_t(B_ * C * Lp_), 0);
  suffix_pos_.assign(std::size_t(B_ * C), 0);
  cross_pos_.assign(std::size_t(B_ * C), 0);
  x_t_.resize(std::size_t(B_ * C * A));
  v_t_.resize(std::size_t(B_ * C * A));
  suffix_x_.resize(std::size_t(B_ * C * E));
  cat_.resize(std::size_t(B_ * C * 2 * E));
  mlp_h_.resize(std::size_t(B_ * C * E));
  time_emb_.resize(std::size_t(E));
}

void SmolVLA::build_prefix(const std::vector<ModelInput>& batch, ModelOutput& out) {
  const auto t0 = std::chrono::steady_clock::now();
  const int64_t B = int64_t(batch.size()), D = text_cfg_.hidden;
  const int64_t H = spec_.image_height, W = spec_.image_width, ncam = int64_t(spec_.cameras.size());
  const int64_t img_elems = 3 * H * W;

  // Cameras: present ones are preprocessed; absent ones follow upstream: up to `empty_cameras` slots are filled
  // with a -1 image and masked out, further absent cameras are dropped from the prefix.
  pixels_.resize(std::size_t(ncam * B * img_elems));
  img_present_.assign(std::size_t(ncam * B), 0);
  std::vector<int64_t> slots(B, 0);  // image slots used per item
  std::vector<std::vector<int64_t>> slot_camera(B);
  for (int64_t b = 0; b < B; ++b) {
    int64_t missing_used = 0;
    for (int64_t c = 0; c < ncam; ++c) {
      auto it = batch[b].images.find(spec_.cameras[c]);
      if (it != batch[b].images.end()) {
        vision::resize_with_pad_normalized(it->second, int(H), int(W), &pixels_[(c * B + b) * img_elems]);
        img_present_[c * B + b] = 1;
        slot_camera[b].push_back(c);
      }
    }
    for (int64_t c = 0; c < ncam; ++c) {
      if (img_present_[c * B + b]) continue;
      const bool real_camera = c < ncam - empty_cameras_;  // not one of the config's synthetic empty cameras
      if (missing_used < empty_cameras_) {
        ++missing_used;
        slot_camera[b].push_back(c);
        if (real_camera) out.warnings[b].push_back("no image for camera '" + spec_.cameras[c] +
                                  "': filled with an empty (masked) image as the checkpoint's empty_cameras allows");
      } else if (real_camera) {
        out.warnings[b].push_back("no image for camera '" + spec_.cameras[c] +
                                  "': camera dropped from the prefix, as upstream does");
      }
      std::fill_n(&pixels_[(c * B + b) * img_elems], img_elems, -1.0f);
    }
    if (slot_camera[b].empty() || std::none_of(slot_camera[b].begin(), slot_camera[b].end(),
                                               [&](int64_t c) { return img_present_[c * B + b]; }))
      throw Error(ErrorCode::invalid_argument, "observation " + std::to_string(b) +
                                                   " has no image for any camera the model knows");
    slots[b] = int64_t(slot_camera[b].size());
  }

  // Language tokens.
  std::vector<std::string> texts;
  for (const auto& item : batch) texts.push_back(item.instruction + (tok_settings_.append_newline ? "\n" : ""));
  text::BatchOptions opts = tokenizer_->defaults;
  opts.padding = tok_settings_.padding == "max_length" ? text::Padding::max_length : text::Padding::longest;
  opts.max_length = tok_settings_.max_length;
  opts.truncation = tok_settings_.truncation;
  opts.pad_right = tok_settings_.pad_right;
  const text::BatchEncoding enc = text::encode_batch(tokenizer_->tokenizer, texts, opts);
  const int64_t L = enc.length;
  out.timings.set("preprocess", ms_since(t0));

  // Vision tower + connector over runs of up to kVisionGroup present images (camera-major order), so the
  // GEMMs see several images at once while activation memory stays bounded for large batches. Masked fillers
  // are skipped: their features never reach an unmasked token.
  const auto t1 = std::chrono::steady_clock::now();
  const int64_t patches = vision_.num_patches(H, W), T = connector_.tokens(patches);
  constexpr int64_t kVisionGroup = 4;
  vision_out_.resize(std::size_t(std::min(ncam * B, kVisionGroup) * patches * vision_.hidden()));
  img_tokens_.resize(std::size_t(ncam * B * T * D));
  for (int64_t i = 0; i < ncam * B;) {
    if (!img_present_[i]) {
      ++i;
      continue;
    }
    int64_t n = 1;
    while (n < kVisionGroup && i + n < ncam * B && img_present_[i + n]) ++n;
    vision_.forward(&pixels_[i * img_elems], n, H, W, vision_out_.data());
    connector_.forward(vision_out_.data(), n, patches, &img_tokens_[i * T * D]);
    i += n;
  }
  out.timings.set("vision", ms_since(t1));
  if (dumping()) {
    for (int64_t c = 0; c < ncam; ++c) {
      dump("pre.pixels." + spec_.cameras[c], Tensor{DType::f32, {B, 3, H, W}, &pixels_[c * B * img_elems], nullptr});
      dump("mid.vision." + spec_.cameras[c], Tensor{DType::f32, {B, T, D}, &img_tokens_[c * B * T * D], nullptr});
    }
    dump("pre.lang_tokens", Tensor{DType::i64, {B, L}, enc.ids.data(), nullptr});
    dump("pre.lang_mask", Tensor{DType::u8, {B, L}, enc.mask.data(), nullptr});
  }

  // Prefix layout per item: image slots, language tokens, state; items shorter than the longest are padded at
  // the end with masked tokens (masked keys get exactly zero attention weight, so batching changes nothing).
  int64_t Lp = 0;
  for (int64_t b = 0; b < B; ++b) Lp = std::max(Lp, slots[b] * T + L + 1);
  Lp = std::max(Lp, prefix_length_);
  ensure_buffers(B, Lp);
  std::fill(prefix_x_.begin(), prefix_x_.end(), 0.f);
  std::fill(prefix_pad_.begin(), prefix_pad_.end(), 0);
  std::fill(prefix_att_.begin(), prefix_att_.end(), 0);
  const float img_scale = float(std::sqrt(double(D)));
  std::vector<float> state(std::size_t(spec_.max_state_dim));
  for (int64_t b = 0; b < B; ++b) {
    float* x = &prefix_x_[b * Lp * D];
    uint8_t* pad = &prefix_pad_[b * Lp];
    int64_t t = 0;
    for (int64_t c : slot_camera[b]) {
      const float* src = &img_tokens_[(c * B + b) * T * D];
      for (int64_t i = 0; i < T * D; ++i) x[t * D + i] = src[i] * img_scale;
      std::fill_n(pad + t, T, img_present_[c * B + b]);
      t += T;
    }
    for (int64_t j = 0; j < L; ++j, ++t) {
      const int64_t id = enc.ids[b * L + j];
      if (id < 0 || id >= text_cfg_.vocab)
        throw Error(ErrorCode::internal, "token id " + std::to_string(id) + " outside the embedding table");
      embed_tokens_.copy_f32(id * D, D, x + t * D);
      for (int64_t i = 0; i < D; ++i) x[t * D + i] *= img_scale;
      pad[t] = enc.mask[b * L + j];
    }
    std::fill(state.begin(), state.end(), 0.f);
    const auto& s = batch[b].state;
    std::copy(s.begin(), s.end(), state.begin());
    state_proj_.forward(state.data(), 1, x + t * D);
    pad[t] = 1;
    prefix_att_[b * Lp + t] = 1;  // image and language tokens do not attend to the state
  }
  if (dumping()) {
    std::vector<float> padded(std::size_t(B * spec_.max_state_dim), 0.f);
    for (int64_t b = 0; b < B; ++b) std::copy(batch[b].state.begin(), batch[b].state.end(), &padded[b * spec_.max_state_dim]);
    dump("pre.state", Tensor{DType::f32, {B, spec_.max_state_dim}, padded.data(), nullptr});
  }

  // make_att_2d_masks: j visible from i when cumsum(att)[j] <= cumsum(att)[i] and both are real tokens.
  for (int64_t b = 0; b < B; ++b) {
    std::vector<int64_t> cum(static_cast<std::size_t>(Lp));
    int64_t acc = 0, pos = 0;
    for (int64_t t = 0; t < Lp; ++t) {
      acc += prefix_att_[b * Lp + t];
      cum[t] = acc;
      pos += prefix_pad_[b * Lp + t];
      prefix_pos_[b * Lp + t] = pos - 1;
    }
    for (int64_t i = 0; i < Lp; ++i)
      for (int64_t j = 0; j < Lp; ++j)
        prefix_mask_[(b * Lp + i) * Lp + j] = cum[j] <= cum[i] && prefix_pad_[b * Lp + i] && prefix_pad_[b * Lp + j];
  }
  if (dumping()) {
    dump("mid.prefix_embs", Tensor{DType::f32, {B, Lp, D}, prefix_x_.data(), nullptr});
    dump("mid.prefix_pad_mask", Tensor{DType::u8, {B, Lp}, prefix_pad_.data(), nullptr});
  }
}

// Runs the VLM over the prefix once, leaving post-RoPE K/V of every layer in the cache.
void SmolVLA::run_prefix() {
  const int64_t B = B_, Lp = Lp_, C = spec_.chunk_size, D = text_cfg_.hidden;
  const int64_t H = text_cfg_.heads, KvH = text_cfg_.kv_heads, hd = text_cfg_.head_dim;
  const int64_t q_dim = H * hd, kv_dim = KvH * hd, qkv_dim = q_dim + 2 * kv_dim, rows = B * Lp;
  const float scale_qk = 1.0f / std::sqrt(float(hd));
  float* x = prefix_x_.data();
  for (std::size_t li = 0; li < vlm_.size(); ++li) {
    const LlamaLayer& L = vlm_[li];
    const bool last = li + 1 == vlm_.size();
    rms_norm(x, rows, D, L.input_norm, text_cfg_.rms_norm_eps, normed_.data());
    // The last layer's output is never read: only its K/V are needed.
    (last ? L.kv : L.qkv).forward(normed_.data(), rows, qkv_.data());
    const int64_t stride = last ? 2 * kv_dim : qkv_dim, k_off = last ? 0 : q_dim;
    for (int64_t b = 0; b < B; ++b) {
      float* kc = &k_cache_[li][b * (Lp + C) * kv_dim];
      float* vc = &v_cache_[li][b * (Lp + C) * kv_dim];
      for (int64_t t = 0; t < Lp; ++t) {
        const float* row = &qkv_[(b * Lp + t) * stride];
        if (!last) std::memcpy(&q_[(b * Lp + t) * q_dim], row, std::size_t(q_dim) * sizeof(float));
        std::memcpy(kc + t * kv_dim, row + k_off, std::size_t(kv_dim) * sizeof(float));
        std::memcpy(vc + t * kv_dim, row + k_off + kv_dim, std::size_t(kv_dim) * sizeof(float));
      }
      rope(kc, 1, Lp, KvH, hd, &prefix_pos_[b * Lp], kRopeWavelength);
      if (last) continue;
      rope(&q_[b * Lp * q_dim], 1, Lp, H, hd, &prefix_pos_[b * Lp], kRopeWavelength);
      attention(&q_[b * Lp * q_dim], q_dim, kc, vc, kv_dim, &prefix_mask_[b * Lp * Lp], 1, Lp, Lp, H, KvH, hd,
                scale_qk, &attn_[b * Lp * q_dim]);
    }
    if (!last) L.finish(attn_.data(), rows, text_cfg_.rms_norm_eps, x, scratch_);
  }
  if (dumping()) {
    std::vector<float> compact(std::size_t(B * Lp * kv_dim));
    for (std::size_t li : {std::size_t(0), vlm_.size() - 1}) {
      for (const auto& [name, cache] : {std::pair{"k", &k_cache_[li]}, std::pair{"v", &v_cache_[li]}}) {
        for (int64_t b = 0; b < B; ++b)
          std::memcpy(&compact[b * Lp * kv_dim], &(*cache)[b * (Lp + C) * kv_dim], std::size_t(Lp * kv_dim) * 4);
        dump(std::string("mid.prefix_") + name + "." + std::to_string(li),
             Tensor{DType::f32, {B, Lp, KvH, hd}, compact.data(), nullptr});
      }
    }
  }

  // Cross-attention K/V: the expert's projections of the (fixed) prefix K/V do not change across denoise
  // steps, so they are computed once per request instead of once per step.
  for (std::size_t li = 0; li < vlm_.size(); ++li) {
    if (cross_k_[li].empty()) continue;
    const LlamaLayer& X = expert_[expert_at_[li]];
    for (int64_t b = 0; b < B; ++b) {
      const float* kc = &k_cache_[li][b * (Lp + C) * kv_dim];
      const float* vc = &v_cache_[li][b * (Lp + C) * kv_dim];
      X.k_in.forward(kc, Lp, &cross_k_[li][b * Lp * kv_dim]);
      X.v_in.forward(vc, Lp, &cross_v_[li][b * Lp * kv_dim]);
    }
  }

  // Masks and positions of the action tokens: they see every real prefix token and, among themselves,
  // causally (each action token is its own attention block); positions continue after the real prefix.
  for (int64_t b = 0; b < B; ++b) {
    int64_t valid = 0;
    for (int64_t t = 0; t < Lp; ++t) valid += prefix_pad_[b * Lp + t];
    for (int64_t i = 0; i < C; ++i) {
      suffix_pos_[b * C + i] = valid + i;
      cross_pos_[b * C + i] = i;
      uint8_t* srow = &self_mask_[(b * C + i) * (Lp + C)];
      uint8_t* crow = &cross_mask_[(b * C + i) * Lp];
      for (int64_t t = 0; t < Lp; ++t) srow[t] = crow[t] = prefix_pad_[b * Lp + t];
      for (int64_t j = 0; j < C; ++j) srow[Lp + j] = j <= i;
    }
  }
}

// One Euler step's velocity: embeds x ([B, chunk, max_action_dim]) with the time, runs the expert against the cached
// prefix, writes the velocity to v (same layout).
void SmolVLA::denoise_step(const float* x_t, float time, float* v) {
  const int64_t B = B_, Lp = Lp_, C = spec_.chunk_size, E = expert_hidden_;
  const int64_t H = text_cfg_.heads, KvH = text_cfg_.kv_heads, hd = text_cfg_.head_dim;
  const int64_t q_dim = H * hd, kv_dim = KvH * hd, qkv_dim = q_dim + 2 * kv_dim, rows = B * C;
  const float scale_qk = 1.0f / std::sqrt(float(hd));

  // Sinusoidal time embedding, computed in float64 as upstream does, then rounded to float32.
  // The fractions follow torch.linspace, which fills the upper half counting back from the end.
  const int64_t half = E / 2;
  const double lin_step = half > 1 ? 1.0 / double(half - 1) : 0.0;
  for (int64_t i = 0; i < half; ++i) {
    const double fraction = i < half / 2 ? double(i) * lin_step : 1.0 - double(half - 1 - i) * lin_step;
    const double period = min_period_ * std::pow(max_period_ / min_period_, fraction);
    const double angle = (1.0 / period) * 2.0 * M_PI * double(time);
    time_emb_[i] = float(std::sin(angle));
    time_emb_[half + i] = float(std::cos(angle));
  }
  // [action_in(x_t), time] -> mlp_in -> silu -> mlp_out.
  action_in_.forward(x_t, rows, cat_.data(), false, /*ldy=*/2 * E);
  for (int64_t r = 0; r < rows; ++r) std::memcpy(&cat_[r * 2 * E + E], time_emb_.data(), std::size_t(E) * sizeof(float));
  time_in_.forward(cat_.data(), rows, mlp_h_.data());
  silu(mlp_h_.data(), rows * E);
  time_out_.forward(mlp_h_.data(), rows, suffix_x_.data());

  float* x = suffix_x_.data();
  for (std::size_t li = 0; li < vlm_.size(); ++li) {
    if (expert_at_[li] < 0) continue;  // no expert layer here: the action stream passes through unchanged
    const LlamaLayer& X = expert_[expert_at_[li]];
    rms_norm(x, rows, E, X.input_norm, text_cfg_.rms_norm_eps, normed_.data());
    if (!X.cross) {
      X.qkv.forward(normed_.data(), rows, qkv_.data());
      for (int64_t b = 0; b < B; ++b) {
        float* kc = &k_cache_[li][b * (Lp + C) * kv_dim];
        float* vc = &v_cache_[li][b * (Lp + C) * kv_dim];
        for (int64_t i = 0; i < C; ++i) {
          const float* row = &qkv_[(b * C + i) * qkv_dim];
          std::memcpy(&q_[(b * C + i) * q_dim], row, std::size_t(q_dim) * sizeof(float));
          std::memcpy(kc + (Lp + i) * kv_dim, row + q_dim, std::size_t(kv_dim) * sizeof(float));
          std::memcpy(vc + (Lp + i) * kv_dim, row + q_dim + kv_dim, std::size_t(kv_dim) * sizeof(float));
        }
        rope(&q_[b * C * q_dim], 1, C, H, hd, &suffix_pos_[b * C], kRopeWavelength);
        rope(kc + Lp * kv_dim, 1, C, KvH, hd, &suffix_pos_[b * C], kRopeWavelength);
        attention(&q_[b * C * q_dim], q_dim, kc, vc, kv_dim, &self_mask_[b * C * (Lp + C)], 1, C, Lp + C, H, KvH, hd,
                  scale_qk, &attn_[b * C * q_dim]);
      }
    } else {
      X.qkv.forward(normed_.data(), rows, q_.data());
      for (int64_t b = 0; b < B; ++b) {
        rope(&q_[b * C * q_dim], 1, C, H, hd, &cross_pos_[b * C], kRopeWavelength);
        attention(&q_[b * C * q_dim], q_dim, &cross_k_[li][b * Lp * kv_dim], &cross_v_[li][b * Lp * kv_dim], kv_dim,
                  &cross_mask_[b * C * Lp], 1, C, Lp, H, KvH, hd, scale_qk, &attn_[b * C * q_dim]);
      }
    }
    X.finish(attn_.data(), rows, text_cfg_.rms_norm_eps, x, scratch_);
  }
  rms_norm(x, rows, E, expert_norm_, text_cfg_.rms_norm_eps, normed_.data());
  action_out_.forward(normed_.data(), rows, v);
}

ModelOutput SmolVLA::predict(const std::vector<ModelInput>& batch) {
  if (batch.empty()) throw Error(ErrorCode::invalid_argument, "predict: empty batch");
  const int64_t B = int64_t(batch.size()), C = spec_.chunk_size, A = spec_.max_action_dim;
  for (int64_t b = 0; b < B; ++b) {
    if (int64_t(batch[b].state.size()) != spec_.state_dim)
      throw Error(ErrorCode::invalid_argument, "observation " + std::to_string(b) + ": state has " +
                                                   std::to_string(batch[b].state.size()) + " values, the model expects " +
                                                   std::to_string(spec_.state_dim));
    if (!batch[b].noise.empty() && int64_t(batch[b].noise.size()) != C * A)
      throw Error(ErrorCode::invalid_argument, "observation " + std::to_string(b) + ": noise has " +
                                                   std::to_string(batch[b].noise.size()) + " values, expected " +
                                                   std::to_string(C) + "x" + std::to_string(A));
  }
  ModelOutput out;
  out.batch = B;
  out.chunk_size = C;
  out.action_dim = spec_.action_dim;
  out.warnings.resize(std::size_t(B));
  build_prefix(batch, out);

  const auto t2 = std::chrono::steady_clock::now();
  run_prefix();
  out.timings.set("prefix", ms_since(t2));

  const auto t3 = std::chrono::steady_clock::now();
  for (int64_t b = 0; b < B; ++b) {
    float* dst = &x_t_[b * C * A];
    if (batch[b].noise.empty()) seeded_normal(batch[b].seed, dst, C * A);
    else std::copy(batch[b].noise.begin(), batch[b].noise.end(), dst);
  }
  // Forward Euler from the noise (t=1) to the actions (t=0), per-item controls (flow_matching.h).
  std::vector<DenoiseControl> controls;
  controls.reserve(batch.size());
  for (const auto& item : batch) controls.push_back(item.denoise);
  std::function<void(const float*)> on_step0;
  if (dumping())
    on_step0 = [&](const float* v) { dump("mid.velocity.step0", Tensor{DType::f32, {B, C, A}, v, nullptr}); };
  out.steps_used = euler_sample(x_t_.data(), v_t_.data(), {B, C, A, spec_.action_dim}, spec_.num_steps, controls,
                                [this](const float* x, float time, float* v) { denoise_step(x, time, v); }, on_step0);
  out.timings.set("denoise", ms_since(t3));

  out.actions.resize(std::size_t(B * C * spec_.action_dim));
  for (int64_t r = 0; r < B * C; ++r)
    std::memcpy(&out.actions[r * spec_.action_dim], &x_t_[r * A], std::size_t(spec_.action_dim) * sizeof(float));
  return out;
}

}  // namespace

std::unique_ptr<Model> load_smolvla(const fs::path& checkpoint_dir, const Json& config, TensorStore weights,
                                    const LoadOptions& options) {
  return std::make_unique<SmolVLA>(checkpoint_dir, config, std::move(weights), options);
}

}  // namespace tether::models
