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
#include "models/gr00t_head.h"
#include "text/tokenizer.h"
#include "text/unicode.h"
#include "vision/gr00t_preprocess.h"

namespace tether::models {

namespace fs = std::filesystem;
using backend::Ptr;

namespace {

constexpr const char* kVisual = "backbone.model.model.visual.";
constexpr const char* kText = "backbone.model.model.language_model.";

class Gr00tN17 final : public Gr00tModel {
 public:
  Gr00tN17(const fs::path& dir, const Json& config, TensorStore store, const LoadOptions& options);

 private:
  Backbone encode_backbone(const ModelInput& in, int64_t item, ModelOutput& out) override;
  std::vector<int32_t> prompt_ids(const std::string& instruction, const std::vector<int64_t>& tokens_per_image) const;
  void rope_tables(const std::vector<int32_t>& ids, const std::vector<vision::PatchGrid>& grids,
                   std::vector<float>& cos, std::vector<float>& sin, std::vector<int64_t>& positions) const;

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

  // Per-request buffers, grown once per shape.
  backend::Array<float> pixels_, merged_, x_, rope_cos_, rope_sin_;
  std::vector<backend::Array<float>> deepstack_;
  backend::Array<int64_t> ids_;
  backend::Array<uint8_t> causal_;
};

Gr00tN17::Gr00tN17(const fs::path& dir, const Json& config, TensorStore store, const LoadOptions& options)
    : Gr00tModel(options) {
  const std::string where = (dir / "config.json").string();
  backend::Backend& be = *be_;
  const cpu::Precision precision = options.precision;
  head_ = Gr00tHeadConfig::from_json(config, where, "nvidia/Cosmos-Reason2-2B");
  read_gr00t_embodiment(dir, options.embodiment);  // an unknown tag fails here, before the backbone loads
  const Json kwargs = gr00t_processor_kwargs(dir);
  const std::string pwhere = gr00t_sidecar(dir, "processor_config.json").string();
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

  weights_ = std::make_unique<Weights>(std::move(store));
  Weights& w = *weights_;
  vision_.load(be, w, kVisual, vcfg, precision);
  embed_ = be.table(w.raw(std::string(kText) + "embed_tokens.weight", {text_cfg_.vocab, text_cfg_.hidden}));
  text_.load(be, w, std::string(kText) + "layers.", text_cfg_, head_.select_layer, precision, false);
  load_head(w, precision);
  fill_spec(gr00t_n17_family(), tokenizer_->source, geometry_.target_h, geometry_.target_w, precision, w.stored_dtype(),
            where);
  add_embodiment(dir, options.embodiment, w);
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

Gr00tModel::Backbone Gr00tN17::encode_backbone(const ModelInput& in, int64_t item, ModelOutput& out) {
  backend::Backend& be = *be_;
  auto t0 = std::chrono::steady_clock::now();
  // Frames: every camera of the embodiment, in its order (upstream has no rule for a missing one).
  std::vector<vision::PixelPatches> frames;
  std::vector<vision::PatchGrid> grids;
  std::vector<int64_t> tokens_per_image;
  int64_t rows = 0;
  for (const std::string& cam : spec().cameras) {
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
  be.synchronize();  // a GPU runs behind the host: time the work, not its queueing
  out.timings.set("vision", out.timings.get("vision") + elapsed_ms(t0));

  // Text: token embeddings with the image rows in place of the image pads, the decoder with the DeepStack features
  // added after its first layers, then the VL norm and self-attention.
  t0 = std::chrono::steady_clock::now();
  grow(be, x_, L * D);
  Backbone p;
  const std::vector<std::pair<int64_t, int64_t>> image_runs =
      embed_prompt(*embed_, ids, image_token_, merged_.at(), M, D, item, ids_, x_.at(), p);
  if (dumping()) dump_array<float>(be, "mid.llm.inputs_embeds", DType::f32, {1, L, D}, x_.at());

  grow(be, rope_cos_, L * text_cfg_.head_dim / 2);
  grow(be, rope_sin_, L * text_cfg_.head_dim / 2);
  be.upload(cs.data(), int64_t(cs.size()), rope_cos_.at());
  be.upload(sn.data(), int64_t(sn.size()), rope_sin_.at());
  upload_causal_mask(L, causal_);
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
  be.synchronize();  // a GPU runs behind the host: time the work, not its queueing
  out.timings.set("backbone", out.timings.get("backbone") + elapsed_ms(t0));
  p.features = x_.at();
  return p;
}

}  // namespace

std::unique_ptr<Model> load_gr00t_n17(const fs::path& dir, const Json& config, TensorStore weights,
                                      const LoadOptions& options) {
  return load_gr00t_embodiment(dir, config, std::move(weights), options, [&](TensorStore store) {
    return std::make_unique<Gr00tN17>(dir, config, std::move(store), options);
  });
}

}  // namespace tether::models
