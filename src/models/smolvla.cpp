// SmolVLA as wiring of the shared blocks: vision tower + pixel-shuffle connector, the truncated VLM decoder over the
// prefix, the interleaved self/cross action expert, and the Euler sampler.
#include "models/smolvla.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <filesystem>
#include <optional>

#include "backend/backend.h"
#include "models/backbone.h"
#include "models/blocks/action_expert.h"
#include "models/blocks/attention_masks.h"
#include "models/blocks/decoder.h"
#include "models/blocks/linear.h"
#include "models/blocks/sampler.h"
#include "models/blocks/vision_tower.h"
#include "text/tokenizer.h"
#include "vision/preprocess.h"

namespace tether::models {

namespace fs = std::filesystem;
using backend::Ptr;

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
  void denoise_step(Ptr<const float> x, float time, Ptr<float> v);
  void ensure_buffers(int64_t batch, int64_t prefix_len);
  double flops(int64_t images, int64_t steps_run) const;
  // Named intermediate from backend memory, copied to the host for the debug hook.

  ModelSpec spec_;
  TokenizerSettings tok_settings_;
  std::optional<text::PretrainedTokenizer> tokenizer_;  // set in the constructor (no empty state)
  int64_t empty_cameras_ = 0, prefix_length_ = -1, self_attn_every_ = 2;
  bool cross_mode_ = true;
  double min_period_ = 4e-3, max_period_ = 4.0;

  std::shared_ptr<backend::Backend> be_;
  std::unique_ptr<Weights> weights_;
  DecoderConfig text_cfg_;
  VisionTower vision_;
  PixelShuffleConnector connector_;
  std::unique_ptr<backend::Table> embed_tokens_;  // stored dtype, rows converted on lookup (only used rows are read)
  DecoderStack vlm_;
  ActionExpert expert_;
  int64_t expert_hidden_ = 0;
  backend::Array<float> expert_norm_;
  std::unique_ptr<backend::LinearWeights> state_proj_, action_in_, action_out_, time_in_, time_out_;

  // Per-request state, sized once per (batch, prefix length) so the denoise loop never allocates. Host vectors hold
  // what is computed on the host (pixels, token ids, masks, positions) before it is uploaded to the backend arrays.
  int64_t B_ = 0, Lp_ = 0;
  std::vector<float> host_pixels_, host_state_;
  std::vector<uint8_t> prefix_pad_, img_present_, host_mask_, host_joint_mask_, host_cross_mask_;
  std::vector<int8_t> prefix_att_;
  std::vector<int64_t> host_pos_, host_joint_pos_, host_cross_pos_;
  backend::Array<float> pixels_, vision_out_, img_tokens_, prefix_x_, state_;
  backend::Array<int64_t> token_ids_, prefix_pos_, suffix_pos_, cross_pos_;
  backend::Array<uint8_t> prefix_mask_, self_mask_, cross_mask_;
  KvCache cache_;
  backend::Array<float> x_t_, v_t_, suffix_x_, cat_, time_emb_, mlp_h_, normed_;
  int64_t images_run_ = 0;  // images through the vision tower in this request (for the flop count)
};

SmolVLA::SmolVLA(const fs::path& dir, const Json& config, TensorStore weights, const LoadOptions& options) {
  const cpu::Precision precision = options.precision;
  spec_.precision = precision;
  be_ = options.backend ? options.backend : backend::make_default_backend();
  spec_.backend = be_->name();
  backend::Backend& be = *be_;
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
  set_single_groups(spec_);

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
  text_cfg_ = DecoderConfig::from_llama_json(json_get<Json>(vlm_cfg, "text_config", vlm_where), vlm_where);
  text_cfg_.rope_wavelength = kRopeWavelength;
  text_cfg_.embedding_scale = float(std::sqrt(double(text_cfg_.hidden)));  // images and text tokens alike
  if (text_cfg_.rms_norm_eps == 1e-6f && !vlm_cfg["text_config"].contains("rms_norm_eps"))
    text_cfg_.rms_norm_eps = 1e-5f;  // SmolVLMConfig's default text config overrides Llama's eps
  const int64_t scale_factor = json_get_or<int64_t>(vlm_cfg, "scale_factor", 2, vlm_where);
  // Loaded as transformers' AutoTokenizer builds it (tokenizer class overrides, truncation side, pad token).
  tokenizer_.emplace(text::load_pretrained_tokenizer(vlm_dir.string()));
  spec_.tokenizer_source = tokenizer_->source;

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
  vision_.load(be, w, vlm_prefix + "vision_model.", vision_cfg, precision);
  connector_.load(be, w, vlm_prefix + "connector.", vision_cfg.hidden, scale_factor, D, precision);
  embed_tokens_ = be.table(w.raw(vlm_prefix + "text_model.embed_tokens.weight", {text_cfg_.vocab, D}));
  // The prefix's last layer feeds nothing but its K/V (the VLM's final norm is never applied on this path).
  vlm_.load(be, w, vlm_prefix + "text_model.layers.", text_cfg_, vlm_layers, precision, /*last_kv_only=*/true);
  const int64_t kv_dim = text_cfg_.kv_heads * text_cfg_.head_dim;
  std::vector<DecoderLayer::Attention> kinds;
  for (int64_t e = 0; e < expert_layers; ++e) {
    // Upstream reshapes k/v to read the VLM's K/V by *expert* index; routing below is by VLM index.
    const bool cross_shaped = cross_mode_ && !(self_attn_every_ > 0 && e % self_attn_every_ == 0);
    kinds.push_back(cross_shaped ? DecoderLayer::Attention::cross : DecoderLayer::Attention::self);
  }
  expert_.load(be, w, expert_prefix + "layers.", text_cfg_, E, expert_intermediate_size(E), kinds, kv_dim, precision);
  expert_norm_ = be.constant(w.f32(expert_prefix + "norm.weight", {E}), E);
  const int64_t multiple = vlm_layers / expert_layers;
  std::vector<ActionExpert::Route> routes;
  for (int64_t i = 0; i < vlm_layers; ++i) {
    if (multiple > 1 && i % multiple != 0) continue;  // no expert layer here: the action stream passes unchanged
    const int64_t e = i / multiple;
    const bool self_route = !cross_mode_ || (self_attn_every_ > 0 && i % self_attn_every_ == 0);
    if (self_route == expert_.layer(e).cross())
      throw Error(ErrorCode::unsupported,
                  where + ": this num_expert_layers/self_attn_every_n_layers combination routes expert layer " +
                      std::to_string(e) + " through the wrong attention kind (upstream fails too)");
    routes.push_back({e, i});
  }
  expert_.set_routes(std::move(routes));
  state_proj_ = load_linear(be, w, "model.state_proj", D, spec_.max_state_dim, true, precision);
  action_in_ = load_linear(be, w, "model.action_in_proj", E, A, true, precision);
  action_out_ = load_linear(be, w, "model.action_out_proj", A, E, true, precision);
  time_in_ = load_linear(be, w, "model.action_time_mlp_in", E, 2 * E, true, precision);
  time_out_ = load_linear(be, w, "model.action_time_mlp_out", E, E, true, precision);
  spec_.weights_dtype = w.stored_dtype();
  w.finish_loading();
  if (spec_.image_height == 0) spec_.image_height = spec_.image_width = vision_cfg.image_size;
}

void SmolVLA::ensure_buffers(int64_t batch, int64_t prefix_len) {
  if (batch == B_ && prefix_len == Lp_) return;
  B_ = batch;
  Lp_ = prefix_len;
  backend::Backend& be = *be_;
  const int64_t D = text_cfg_.hidden, E = expert_hidden_, C = spec_.chunk_size, A = spec_.max_action_dim;
  const int64_t kv_dim = text_cfg_.kv_heads * text_cfg_.head_dim;
  prefix_x_ = be.alloc<float>(B_ * Lp_ * D);
  state_ = be.alloc<float>(B_ * spec_.max_state_dim);
  cache_.resize(be, vlm_.layers(), B_, Lp_ + C, kv_dim);
  prefix_pos_ = be.alloc<int64_t>(B_ * Lp_);
  prefix_mask_ = be.alloc<uint8_t>(B_ * Lp_ * Lp_);
  self_mask_ = be.alloc<uint8_t>(B_ * C * (Lp_ + C));
  cross_mask_ = be.alloc<uint8_t>(B_ * C * Lp_);
  suffix_pos_ = be.alloc<int64_t>(B_ * C);
  cross_pos_ = be.alloc<int64_t>(B_ * C);
  x_t_ = be.alloc<float>(B_ * C * A);
  v_t_ = be.alloc<float>(B_ * C * A);
  suffix_x_ = be.alloc<float>(B_ * C * E);
  cat_ = be.alloc<float>(B_ * C * 2 * E);
  mlp_h_ = be.alloc<float>(B_ * C * E);
  normed_ = be.alloc<float>(B_ * C * E);
  time_emb_ = be.alloc<float>(E);
}

void SmolVLA::build_prefix(const std::vector<ModelInput>& batch, ModelOutput& out) {
  backend::Backend& be = *be_;
  const auto t0 = std::chrono::steady_clock::now();
  const int64_t B = int64_t(batch.size()), D = text_cfg_.hidden;
  const int64_t H = spec_.image_height, W = spec_.image_width, ncam = int64_t(spec_.cameras.size());
  const int64_t img_elems = 3 * H * W;

  // Cameras: present ones are preprocessed; absent ones follow upstream: up to `empty_cameras` slots are filled
  // with a -1 image and masked out, further absent cameras are dropped from the prefix.
  host_pixels_.resize(std::size_t(ncam * B * img_elems));
  img_present_.assign(std::size_t(ncam * B), 0);
  std::vector<int64_t> slots(B, 0);  // image slots used per item
  std::vector<std::vector<int64_t>> slot_camera(B);
  for (int64_t b = 0; b < B; ++b) {
    int64_t missing_used = 0;
    for (int64_t c = 0; c < ncam; ++c) {
      auto it = batch[b].images.find(spec_.cameras[c]);
      if (it != batch[b].images.end()) {
        vision::resize_with_pad_normalized(it->second, int(H), int(W), &host_pixels_[(c * B + b) * img_elems]);
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
      std::fill_n(&host_pixels_[(c * B + b) * img_elems], img_elems, -1.0f);
    }
    if (slot_camera[b].empty() || std::none_of(slot_camera[b].begin(), slot_camera[b].end(),
                                               [&](int64_t c) { return img_present_[c * B + b]; }))
      throw Error(ErrorCode::invalid_argument, "observation " + std::to_string(b) +
                                                   " has no image for any camera the model knows");
    slots[b] = int64_t(slot_camera[b].size());
  }
  if (pixels_.size() < int64_t(host_pixels_.size())) pixels_ = be.alloc<float>(int64_t(host_pixels_.size()));
  be.upload(host_pixels_.data(), int64_t(host_pixels_.size()), pixels_.at());

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
  for (int64_t id : enc.ids)
    if (id < 0 || id >= text_cfg_.vocab)
      throw Error(ErrorCode::internal, "token id " + std::to_string(id) + " outside the embedding table");
  token_ids_ = be.alloc<int64_t>(B * L);
  be.upload(enc.ids.data(), B * L, token_ids_.at());
  out.timings.set("preprocess", ms_since(t0));

  // Vision tower + connector over runs of up to kVisionGroup present images (camera-major order), so the
  // GEMMs see several images at once while activation memory stays bounded for large batches. Masked fillers
  // are skipped: their features never reach an unmasked token.
  const auto t1 = std::chrono::steady_clock::now();
  const int64_t patches = vision_.num_patches(H, W), T = connector_.tokens(patches);
  constexpr int64_t kVisionGroup = 4;
  const int64_t vision_rows = std::min(ncam * B, kVisionGroup) * patches * vision_.hidden();
  if (vision_out_.size() < vision_rows) vision_out_ = be.alloc<float>(vision_rows);
  if (img_tokens_.size() < ncam * B * T * D) img_tokens_ = be.alloc<float>(ncam * B * T * D);
  images_run_ = 0;
  for (int64_t i = 0; i < ncam * B;) {
    if (!img_present_[i]) {
      ++i;
      continue;
    }
    int64_t n = 1;
    while (n < kVisionGroup && i + n < ncam * B && img_present_[i + n]) ++n;
    vision_.forward(be, pixels_.at(i * img_elems), n, H, W, vision_out_.at());
    connector_.forward(be, vision_out_.at(), n, patches, img_tokens_.at(i * T * D));
    images_run_ += n;
    i += n;
  }
  be_->synchronize();  // a GPU runs behind the host: time the work, not its queueing
  out.timings.set("vision", ms_since(t1));
  if (dumping()) {
    for (int64_t c = 0; c < ncam; ++c) {
      dump("pre.pixels." + spec_.cameras[c], Tensor{DType::f32, {B, 3, H, W}, &host_pixels_[c * B * img_elems], nullptr});
      dump_array<float>(*be_, "mid.vision." + spec_.cameras[c], DType::f32, {B, T, D}, img_tokens_.at(c * B * T * D));
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
  prefix_pad_.assign(std::size_t(B * Lp), 0);
  prefix_att_.assign(std::size_t(B * Lp), 0);
  host_state_.assign(std::size_t(B * spec_.max_state_dim), 0.f);
  for (int64_t b = 0; b < B; ++b) std::copy(batch[b].state.begin(), batch[b].state.end(), &host_state_[b * spec_.max_state_dim]);
  be.upload(host_state_.data(), B * spec_.max_state_dim, state_.at());
  // Padding rows stay zero: they are masked, but their values still pass through the layers.
  std::vector<float> zeros(std::size_t(Lp * D), 0.f);
  const float embed_scale = text_cfg_.embedding_scale;
  for (int64_t b = 0; b < B; ++b) {
    const Ptr<float> x = prefix_x_.at(b * Lp * D);
    uint8_t* pad = &prefix_pad_[b * Lp];
    int64_t t = 0;
    for (int64_t c : slot_camera[b]) {
      be.copy_rows(img_tokens_.at((c * B + b) * T * D), 0, x + t * D, 0, 1, T * D);
      be.scale(x + t * D, T * D, embed_scale);
      std::fill_n(pad + t, T, img_present_[c * B + b]);
      t += T;
    }
    be.gather_rows(*embed_tokens_, token_ids_.at(b * L), L, embed_scale, x + t * D);
    for (int64_t j = 0; j < L; ++j) pad[t + j] = enc.mask[b * L + j];
    t += L;
    be.linear(*state_proj_, state_.at(b * spec_.max_state_dim), 1, x + t * D);
    pad[t] = 1;
    prefix_att_[b * Lp + t] = 1;  // image and language tokens do not attend to the state
    ++t;
    if (t < Lp) be.upload(zeros.data(), (Lp - t) * D, x + t * D);
  }
  if (dumping()) dump("pre.state", Tensor{DType::f32, {B, spec_.max_state_dim}, host_state_.data(), nullptr});

  prefix_masks(prefix_pad_, prefix_att_, B, Lp, host_mask_, host_pos_);
  be.upload(host_mask_.data(), B * Lp * Lp, prefix_mask_.at());
  be.upload(host_pos_.data(), B * Lp, prefix_pos_.at());
  if (dumping()) {
    dump_array<float>(*be_, "mid.prefix_embs", DType::f32, {B, Lp, D}, prefix_x_.at());
    dump("mid.prefix_pad_mask", Tensor{DType::u8, {B, Lp}, prefix_pad_.data(), nullptr});
  }
}

// Runs the VLM over the prefix once, leaving post-RoPE K/V of every layer in the cache, then what the expert needs.
void SmolVLA::run_prefix() {
  backend::Backend& be = *be_;
  const int64_t B = B_, Lp = Lp_, C = spec_.chunk_size;
  const int64_t KvH = text_cfg_.kv_heads, hd = text_cfg_.head_dim;
  vlm_.forward(be, prefix_x_.at(), B, Lp, prefix_pos_.at(), prefix_mask_.at(), cache_);
  dump_prefix_kv(be, cache_.k, cache_.v, cache_.capacity, B, Lp, KvH, hd);
  expert_.prepare(be, cache_, Lp);
  // Action tokens see every real prefix token and, among themselves, causally (each is its own attention block);
  // positions continue after the real prefix.
  causal_suffix_masks(prefix_pad_, B, Lp, C, host_joint_mask_, host_cross_mask_, host_joint_pos_, host_cross_pos_);
  be.upload(host_joint_mask_.data(), B * C * (Lp + C), self_mask_.at());
  be.upload(host_cross_mask_.data(), B * C * Lp, cross_mask_.at());
  be.upload(host_joint_pos_.data(), B * C, suffix_pos_.at());
  be.upload(host_cross_pos_.data(), B * C, cross_pos_.at());
}

// One Euler step's velocity: embeds x ([B, chunk, max_action_dim]) with the time, runs the expert against the cached
// prefix, writes the velocity to v (same layout).
void SmolVLA::denoise_step(Ptr<const float> x_t, float time, Ptr<float> v) {
  backend::Backend& be = *be_;
  const int64_t B = B_, C = spec_.chunk_size, E = expert_hidden_, rows = B * C;
  // [action_in(x_t), time] -> mlp_in -> silu -> mlp_out.
  be.time_embedding(double(time), E, min_period_, max_period_, time_emb_.at());
  be.linear(*action_in_, x_t, rows, cat_.at(), false, /*ldy=*/2 * E);
  be.copy_rows(time_emb_.at(), 0, cat_.at(E), 2 * E, rows, E);
  be.linear(*time_in_, cat_.at(), rows, mlp_h_.at());
  be.activate(mlp_h_.at(), rows * E, backend::Activation::silu);
  be.linear(*time_out_, mlp_h_.at(), rows, suffix_x_.at());
  expert_.forward(be, suffix_x_.at(), B, C, cache_, Lp_, suffix_pos_.at(), self_mask_.at(), cross_pos_.at(),
                  cross_mask_.at());
  be.rms_norm(suffix_x_.at(), rows, E, expert_norm_.at(), text_cfg_.rms_norm_eps, normed_.at());
  be.linear(*action_out_, normed_.at(), rows, v);
}

double SmolVLA::flops(int64_t images, int64_t steps_run) const {
  const int64_t B = B_, C = spec_.chunk_size, Lp = Lp_, H = spec_.image_height, W = spec_.image_width;
  const int64_t patches = vision_.num_patches(H, W);
  double f = vision_.flops(images, H, W) + connector_.flops(images, patches);
  f += linear_flops(*state_proj_, B) + vlm_.flops(B, Lp).total() + expert_.prepare_flops(B, Lp);
  const double step = linear_flops(*action_in_, B * C) + linear_flops(*time_in_, B * C) +
                      linear_flops(*time_out_, B * C) + expert_.forward_flops(B, C, Lp) +
                      linear_flops(*action_out_, B * C);
  return f + double(steps_run) * step;
}

ModelOutput SmolVLA::predict(const std::vector<ModelInput>& batch) {
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
  sample_actions(*be_, batch, x_t_.at(), v_t_.at(), Schedule{1.0, 0.0, spec_.num_steps},
                 [this](Ptr<const float> x, float time, Ptr<float> v) { denoise_step(x, time, v); }, on_step0, out);
  // Every item runs until the last one stops: the batch's steps are the most any item used.
  out.flops = flops(images_run_, *std::max_element(out.steps_used.begin(), out.steps_used.end()));
  return out;
}

}  // namespace

std::unique_ptr<Model> load_smolvla(const fs::path& checkpoint_dir, const Json& config, TensorStore weights,
                                    const LoadOptions& options) {
  return std::make_unique<SmolVLA>(checkpoint_dir, config, std::move(weights), options);
}

}  // namespace tether::models
