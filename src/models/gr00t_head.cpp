// The GR00T action head and sampler shared by N1.7 and N1.6, and the processor_config.json readers (see gr00t_head.h).
#include "models/gr00t_head.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <map>

#include "core/error.h"
#include "models/blocks/linear.h"
#include "text/unicode.h"

namespace tether::models {

namespace fs = std::filesystem;
using backend::Activation;
using backend::Ptr;

fs::path gr00t_sidecar(const fs::path& dir, const std::string& name) {
  if (fs::is_regular_file(dir / name) || !fs::is_regular_file(dir / "processor" / name)) return dir / name;
  return dir / "processor" / name;
}

namespace {

// processor_config.json, checked to hold a processor_kwargs object.
Json gr00t_processor_config(const fs::path& dir) {
  const fs::path p = gr00t_sidecar(dir, "processor_config.json");
  if (!fs::is_regular_file(p)) throw Error(ErrorCode::not_found, p.string() + ": missing (GR00T's processing settings)");
  Json j = read_json_file(p.string());
  if (!j.contains("processor_kwargs") || !j.at("processor_kwargs").is_object())
    throw Error(ErrorCode::format, p.string() + ": no processor_kwargs object");
  return j;
}

}  // namespace

// processor_config.json's processor_kwargs (the checkpoint's processing settings).
Json gr00t_processor_kwargs(const fs::path& dir) { return gr00t_processor_config(dir).at("processor_kwargs"); }

namespace {

constexpr const char* kHead = "action_head.";

// A modality config enum as lerobot's config_value reads it: lower case, "xyz_rot6d" spelled "xyz+rot6d".
std::string config_value(const Json& v) {
  if (!v.is_string()) return "";
  std::string s = v.get<std::string>();
  std::transform(s.begin(), s.end(), s.begin(), [](unsigned char c) { return char(std::tolower(c)); });
  if (s == "xyz_rot6d") return "xyz+rot6d";
  if (s == "xyz_rotvec") return "xyz+rotvec";
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

// The relative action groups (action_configs rep RELATIVE) of an embodiment read with use_relative_action: their
// min/max from statistics.json's relative_action (one row, or one per chunk step), and the state group each is
// anchored to (state_key, else its own name). Fills e.relative and turns e.action_lo/hi into per-row bounds when a
// group has per-step statistics.
void read_relative_groups(const Json& action, const Json& stats, const std::string& stats_where,
                          const std::string& where, Gr00tEmbodiment& e) {
  const Json configs = action.value("action_configs", Json::array());
  const int64_t rows = e.action_horizon, dim = int64_t(e.action_lo.size());
  struct Bounds {
    int64_t offset, width;
    std::vector<std::vector<float>> lo, hi;  // one row, or one per step
  };
  std::vector<Bounds> relative_bounds;
  int64_t offset = 0;
  for (std::size_t i = 0; i < e.action_groups.size(); ++i) {
    const ModalityGroup& g = e.action_groups[i];
    const Json cfg = i < configs.size() && configs[i].is_object() ? configs[i] : Json::object();
    if (config_value(cfg.value("rep", Json("absolute"))) != "relative") {
      offset += g.dim;
      continue;
    }
    const std::string type = config_value(cfg.value("type", Json(""))), format = config_value(cfg.value("format", Json("")));
    RelativeAction r;
    r.name = g.name;
    r.action_offset = offset;
    r.dim = g.dim;
    if (type == "non_eef") r.kind = RelativeAction::Kind::joint;
    else if (type == "eef" && format == "xyz+rot6d") r.kind = RelativeAction::Kind::eef_xyz_rot6d;
    else
      throw Error(ErrorCode::unsupported, where + ": relative action '" + g.name + "' is " + type + " " + format +
                                              " (supported: NON_EEF, and EEF in XYZ_ROT6D, as lerobot decodes them)");
    const std::string state_key = cfg.value("state_key", Json(nullptr)).is_string()
                                      ? cfg.at("state_key").get<std::string>()
                                      : g.name;
    int64_t state_offset = 0;
    bool found = false;
    for (const ModalityGroup& s : e.state_groups) {
      if (s.name == state_key) {
        if (s.dim != g.dim)
          throw Error(ErrorCode::format, where + ": relative action '" + g.name + "' has " + std::to_string(g.dim) +
                                             " values, its state '" + state_key + "' " + std::to_string(s.dim));
        found = true;
        break;
      }
      state_offset += s.dim;
    }
    if (!found)
      throw Error(ErrorCode::format, where + ": relative action '" + g.name + "' names state '" + state_key +
                                         "', which the embodiment does not have");
    if (r.kind == RelativeAction::Kind::eef_xyz_rot6d && g.dim != 9)
      throw Error(ErrorCode::format, where + ": relative EEF action '" + g.name + "' has " + std::to_string(g.dim) +
                                         " values; xyz+rot6d has 9");
    r.state_offset = state_offset;
    // Its bounds: relative_action's min/max (never the percentiles), [D] or [steps][D].
    const Json& per_key = stats.value("relative_action", Json::object());
    if (!per_key.contains(g.name))
      throw Error(ErrorCode::format, stats_where + ": no relative_action statistics for '" + g.name + "'");
    Bounds b{offset, g.dim, {}, {}};
    for (const char* name : {"min", "max"}) {
      const Json& v = per_key.at(g.name).value(name, Json(nullptr));
      auto& out = std::string(name) == "min" ? b.lo : b.hi;
      if (v.is_array() && !v.empty() && v[0].is_array()) out = v.get<std::vector<std::vector<float>>>();
      else if (v.is_array()) out = {v.get<std::vector<float>>()};
      else throw Error(ErrorCode::format, stats_where + ": relative_action '" + g.name + "' has no " + name);
      for (const auto& row : out)
        if (int64_t(row.size()) != g.dim)
          throw Error(ErrorCode::format, stats_where + ": relative_action '" + g.name + "' " + name + " rows have " +
                                             std::to_string(row.size()) + " values, expected " + std::to_string(g.dim));
      if (out.size() > 1 && int64_t(out.size()) < rows)
        throw Error(ErrorCode::format, stats_where + ": relative_action '" + g.name + "' " + name + " has " +
                                           std::to_string(out.size()) + " steps for a chunk of " + std::to_string(rows));
    }
    if (b.lo.size() > 1 || b.hi.size() > 1) e.action_bound_rows = rows;
    relative_bounds.push_back(std::move(b));
    e.relative.push_back(r);
    offset += g.dim;
  }
  // The bounds, row by row: the absolute groups' repeated, the relative ones' from their row (or their only one).
  const int64_t R = e.action_bound_rows;
  std::vector<float> lo(std::size_t(R * dim)), hi(std::size_t(R * dim));
  for (int64_t r = 0; r < R; ++r)
    for (int64_t c = 0; c < dim; ++c) lo[std::size_t(r * dim + c)] = e.action_lo[std::size_t(c)],
                                      hi[std::size_t(r * dim + c)] = e.action_hi[std::size_t(c)];
  for (const Bounds& b : relative_bounds)
    for (int64_t r = 0; r < R; ++r)
      for (int64_t c = 0; c < b.width; ++c) {
        const std::size_t at = std::size_t(r * dim + b.offset + c);
        lo[at] = b.lo[b.lo.size() > 1 ? std::size_t(r) : 0][std::size_t(c)];
        hi[at] = b.hi[b.hi.size() > 1 ? std::size_t(r) : 0][std::size_t(c)];
      }
  e.action_lo = std::move(lo);
  e.action_hi = std::move(hi);
}

// Isaac-GR00T's N1.6 StateActionProcessor decodes the action groups listed in the action modality's
// mean_std_embedding_keys with their mean/std (lerobot's N1.7 steps ignore the key). Fills e.action_mean_std,
// e.action_mean and e.action_std.
void read_mean_std_actions(const Json& action, const Json& stats, const std::string& stats_where,
                           const std::string& where, Gr00tEmbodiment& e) {
  const Json keys = action.value("mean_std_embedding_keys", Json(nullptr));
  if (!keys.is_array() || keys.empty()) return;
  int64_t dim = 0;
  for (const ModalityGroup& g : e.action_groups) dim += g.dim;
  e.action_mean_std.assign(std::size_t(dim), 0.f);
  e.action_mean.assign(std::size_t(dim), 0.f);
  e.action_std.assign(std::size_t(dim), 0.f);
  int64_t offset = 0;
  for (const ModalityGroup& g : e.action_groups) {
    const bool listed = std::any_of(keys.begin(), keys.end(), [&](const Json& k) { return k == Json(g.name); });
    if (listed) {
      for (const RelativeAction& r : e.relative)
        if (r.name == g.name)
          throw Error(ErrorCode::unsupported, where + ": action '" + g.name + "' is both relative and decoded with " +
                                                  "mean/std, which Tether does not support");
      const Json& s = stats.at("action").at(g.name);
      for (const char* name : {"mean", "std"}) {
        const Json& v = s.value(name, Json(nullptr));
        if (!v.is_array() || int64_t(v.size()) != g.dim)
          throw Error(ErrorCode::format, stats_where + ": action '" + g.name + "' is decoded with mean/std " +
                                             "(mean_std_embedding_keys) but its " + name + " is not " +
                                             std::to_string(g.dim) + " values");
        auto& out = std::string(name) == "mean" ? e.action_mean : e.action_std;
        for (int64_t c = 0; c < g.dim; ++c) out[std::size_t(offset + c)] = v[std::size_t(c)].get<float>();
      }
      for (int64_t c = 0; c < g.dim; ++c) e.action_mean_std[std::size_t(offset + c)] = 1.f;
    }
    offset += g.dim;
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
  const Json processor = gr00t_processor_config(dir);
  const Json& kwargs = processor.at("processor_kwargs");
  const std::string where = gr00t_sidecar(dir, "processor_config.json").string();
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
  e.modality_config = m;

  const fs::path ids_path = gr00t_sidecar(dir, "embodiment_id.json");
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
  const fs::path stats_path = gr00t_sidecar(dir, "statistics.json");
  if (!fs::is_regular_file(stats_path))
    throw Error(ErrorCode::not_found, stats_path.string() + ": missing (GR00T's normalisation statistics)");
  const Json stats = read_json_file(stats_path.string());
  if (!stats.contains(tag)) throw Error(ErrorCode::format, stats_path.string() + ": no statistics for '" + tag + "'");
  // lerobot's N1.7 processor step defaults use_percentiles to true, Isaac-GR00T's Gr00tN1d6Processor to false.
  const bool n16 = processor.value("processor_class", Json("")) == Json("Gr00tN1d6Processor");
  const bool percentiles = json_get_or<bool>(kwargs, "use_percentiles", !n16, where);
  read_groups(m, stats.at(tag), "state", percentiles, stats_path.string(), e.state_groups, e.state_lo, e.state_hi);
  read_groups(m, stats.at(tag), "action", percentiles, stats_path.string(), e.action_groups, e.action_lo, e.action_hi);
  // lerobot reads the relative groups only with use_relative_action; without it a RELATIVE group decodes as an
  // absolute one, with the action statistics.
  if (json_get_or<bool>(kwargs, "use_relative_action", false, where))
    read_relative_groups(action, stats.at(tag), stats_path.string(), where, e);
  if (n16) read_mean_std_actions(action, stats.at(tag), stats_path.string(), where, e);
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
Gr00tHeadConfig Gr00tHeadConfig::from_json(const Json& c, const std::string& where,
                                        const std::string& default_model_name) {
  Gr00tHeadConfig h;
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
  h.model_name = json_get_or<std::string>(c, "model_name", default_model_name, where);
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

namespace {

// A category-specific linear layer (`W` [categories, in, out], `b` [categories, out]) for one category, packed as an
// ordinary linear layer (its W is stored input-major, the transpose of nn.Linear's). Only that category's rows are
// converted: the other embodiments' rows never stay resident.
std::unique_ptr<backend::LinearWeights> load_category_linear(backend::Backend& be, Weights& w, const std::string& name,
                                                             int64_t categories, int64_t in, int64_t out, int64_t id,
                                                             cpu::Precision precision) {
  if (id < 0 || id >= categories)
    throw Error(ErrorCode::format, name + ": embodiment row " + std::to_string(id) + " is outside its " +
                                       std::to_string(categories) + " rows");
  std::vector<float> W(static_cast<std::size_t>(in * out)), b(static_cast<std::size_t>(out));
  w.raw(name + ".W", {categories, in, out}).copy_f32(id * in * out, in * out, W.data());
  w.raw(name + ".b", {categories, out}).copy_f32(id * out, out, b.data());
  std::vector<float> t(static_cast<std::size_t>(in * out));
  for (int64_t i = 0; i < in; ++i)
    for (int64_t o = 0; o < out; ++o) t[std::size_t(o * in + i)] = W[std::size_t(i * out + o)];
  return be.pack_linear(t.data(), out, in, b.data(), precision);
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

}  // namespace

void grow(backend::Backend& be, backend::Array<float>& a, int64_t n) {
  if (a.size() < n) a = be.alloc<float>(n);
}

Gr00tModel::Gr00tModel(const LoadOptions& options)
    : be_(options.backend ? options.backend : backend::make_default_backend()) {}

void Gr00tModel::head_state(const ModelInput& in, float* out) const {
  std::copy(in.state.begin(), in.state.end(), out);
}

std::vector<std::pair<int64_t, int64_t>> Gr00tModel::embed_prompt(const backend::Table& embed,
                                                                  const std::vector<int32_t>& ids, int32_t image_token,
                                                                  Ptr<const float> rows, int64_t row_count,
                                                                  int64_t width, int64_t item,
                                                                  backend::Array<int64_t>& ids_buffer, Ptr<float> x,
                                                                  Backbone& b) {
  backend::Backend& be = *be_;
  const int64_t L = int64_t(ids.size());
  if (ids_buffer.size() < L) ids_buffer = be.alloc<int64_t>(L);
  const std::vector<int64_t> ids64(ids.begin(), ids.end());
  be.upload(ids64.data(), L, ids_buffer.at());
  be.gather_rows(embed, ids_buffer.at(), L, 1.0f, x);
  b.len = L;
  b.image_mask.assign(std::size_t(L), 0);
  std::vector<std::pair<int64_t, int64_t>> runs;
  int64_t image_rows = 0;
  for (int64_t i = 0; i < L;) {
    if (ids[std::size_t(i)] != image_token) {
      ++i;
      continue;
    }
    int64_t j = i;
    while (j < L && ids[std::size_t(j)] == image_token) b.image_mask[std::size_t(j++)] = 1;
    runs.emplace_back(i, j - i);
    image_rows += j - i;
    i = j;
  }
  if (image_rows != row_count)
    throw Error(ErrorCode::invalid_argument, "observation " + std::to_string(item) + ": the prompt has " +
                                                 std::to_string(image_rows) + " image tokens for " +
                                                 std::to_string(row_count) +
                                                 " image rows (does the instruction hold image tokens of its own?)");
  int64_t row = 0;
  for (const auto& [first, n] : runs) {
    be.copy_rows(rows + row * width, width, x + first * width, width, n, width);
    row += n;
  }
  return runs;
}

void Gr00tModel::upload_causal_mask(int64_t len, backend::Array<uint8_t>& mask) {
  std::vector<uint8_t> causal(std::size_t(len * len), 0);
  for (int64_t i = 0; i < len; ++i)
    for (int64_t j = 0; j <= i; ++j) causal[std::size_t(i * len + j)] = 1;
  if (mask.size() < len * len) mask = be_->alloc<uint8_t>(len * len);
  be_->upload(causal.data(), len * len, mask.at());
}

void Gr00tModel::load_head(Weights& w, cpu::Precision precision) {
  backend::Backend& be = *be_;
  const int64_t D = head_.backbone_dim, Din = head_.input_dim;
  if (head_.use_vlln) {
    vlln_w_ = be.constant(w.f32(std::string(kHead) + "vlln.weight", {D}), D);
    vlln_b_ = be.constant(w.f32(std::string(kHead) + "vlln.bias", {D}), D);
  }
  vl_attention_.load(be, w, std::string(kHead) + "vl_self_attention.", head_.vl_layers, head_.vl_heads,
                     head_.vl_head_dim, precision);
  dit_.load(be, w, std::string(kHead) + "model.", head_.dit, precision);
  if (head_.add_pos_embed)
    action_pos_ = be.constant(w.f32(std::string(kHead) + "position_embedding.weight", {head_.max_seq_len, Din}), head_.action_horizon * Din);
}

void Gr00tModel::fill_spec(const FamilyDescriptor& family, const std::string& tokenizer_source, int64_t image_h,
                           int64_t image_w, cpu::Precision precision, const std::string& weights_dtype,
                           const std::string& where) {
  ModelSpec& s = shared_spec_;
  s.family = family.name;
  s.backend = be_->name();
  s.stages = family.stages;
  s.missing_camera_rule = family.missing_camera_rule;
  s.tokenizer = tokenizer_kind_name(family.tokenizer);
  s.tokenizer_source = tokenizer_source;
  s.every_camera_required = true;
  s.state_key = "state";
  s.action_key = "action";
  s.max_state_dim = head_.max_state_dim;
  s.max_action_dim = head_.max_action_dim;
  s.sampled_chunk = head_.action_horizon;
  s.num_steps = head_.steps;
  s.rtc = RtcMethod::inpainting;  // GR00T's own real-time chunking (sampler.h)
  s.rtc_ramp_rate = head_.rtc_ramp_rate;
  s.image_height = image_h;
  s.image_width = image_w;
  s.precision = precision;
  s.weights_dtype = weights_dtype;
  where_ = where;
}

std::size_t Gr00tModel::add_embodiment(const fs::path& dir, const std::string& tag, Weights& w) {
  Gr00tEmbodiment e = read_gr00t_embodiment(dir, tag);
  for (std::size_t i = 0; i < embodiments_.size(); ++i)
    if (embodiments_[i]->embodiment.tag == e.tag) return i;
  auto em = std::make_unique<Embodied>();
  ModelSpec& s = em->spec;
  s = shared_spec_;
  s.embodiment = e.tag;
  s.modality_config = e.modality_config;
  s.cameras = e.cameras;
  s.state_groups = e.state_groups;
  s.action_groups = e.action_groups;
  s.state_dim = 0;
  for (const auto& g : s.state_groups) s.state_dim += g.dim;
  s.action_dim = 0;
  for (const auto& g : s.action_groups) s.action_dim += g.dim;
  s.chunk_size = std::min(e.action_horizon, head_.action_horizon);
  s.relative_actions = !e.relative.empty();
  if (s.state_dim > head_.max_state_dim || s.action_dim > head_.max_action_dim)
    throw Error(ErrorCode::format, where_ + ": embodiment '" + e.tag + "' has more state or action values than "
                                            "max_state_dim / max_action_dim");
  backend::Backend& be = *be_;
  const cpu::Precision precision = shared_spec_.precision;
  const int64_t C = head_.num_embodiments, id = e.id, S = head_.max_state_dim, A = head_.max_action_dim,
                Din = head_.input_dim, Hd = head_.hidden;
  const std::string h = kHead;
  em->state1 = load_category_linear(be, w, h + "state_encoder.layer1", C, S, Hd, id, precision);
  em->state2 = load_category_linear(be, w, h + "state_encoder.layer2", C, Hd, Din, id, precision);
  em->act1 = load_category_linear(be, w, h + "action_encoder.W1", C, A, Din, id, precision);
  em->act2 = load_category_linear(be, w, h + "action_encoder.W2", C, 2 * Din, Din, id, precision);
  em->act3 = load_category_linear(be, w, h + "action_encoder.W3", C, Din, Din, id, precision);
  em->dec1 = load_category_linear(be, w, h + "action_decoder.layer1", C, Hd, Hd, id, precision);
  em->dec2 = load_category_linear(be, w, h + "action_decoder.layer2", C, Hd, A, id, precision);
  add_state_encoding(dir, e);
  em->embodiment = std::move(e);
  embodiments_.push_back(std::move(em));
  return embodiments_.size() - 1;
}

void Gr00tModel::velocity(int64_t B, Ptr<const float> x, float time, Ptr<float> v) {
  backend::Backend& be = *be_;
  const int64_t H = head_.action_horizon, A = head_.max_action_dim, Din = head_.input_dim, T = H + 1;
  // The step index from the time (k / steps), and its bucket as upstream computes it: int((k / steps) * buckets).
  const int64_t k = std::llround(double(time) * double(head_.steps));
  const int64_t bucket = int64_t((double(k) / double(head_.steps)) * double(head_.buckets));
  const std::string step = dumping() ? "step" + std::to_string(k) : std::string();
  const Embodied& em = active();

  // Action encoder: W1(x), then [W1(x) | sinusoid(bucket)] -> W2 -> swish -> W3, plus the position table. The
  // sinusoid is one row, broadcast into every action row.
  be.linear(*em.act1, x, B * H, act_in_.at(), false, 2 * Din);
  host_sinusoid_.resize(std::size_t(Din));
  action_time_sinusoid(bucket, Din, host_sinusoid_.data());
  be.upload(host_sinusoid_.data(), Din, act_mid_.at());
  be.copy_rows(act_mid_.at(), 0, act_in_.at(Din), 2 * Din, B * H, Din);
  be.linear(*em.act2, act_in_.at(), B * H, act_mid_.at());
  be.activate(act_mid_.at(), B * H * Din, Activation::silu);
  // Tokens: the state token, then the encoded actions (with their positions), per item.
  for (int64_t b = 0; b < B; ++b) {
    be.linear(*em.act3, act_mid_.at(b * H * Din), H, tokens_.at((b * T + 1) * Din), false, 0);
    if (dumping() && k == 0 && b == 0)
      dump_array<float>(be, "mid.action_encoder.step0", DType::f32, {1, H, Din}, tokens_.at(Din));
    if (head_.add_pos_embed) be.add(tokens_.at((b * T + 1) * Din), action_pos_.at(), H * Din, tokens_.at((b * T + 1) * Din));
    be.copy_rows(state_tok_.at(b * Din), Din, tokens_.at(b * T * Din), Din, 1, Din);
  }
  // DiT at this time, then the decoder; the velocity is the action rows.
  if (dumping()) {
    dit_.time_embedding(be, bucket, B, temb_.at());
    dump_array<float>(be, "mid.temb." + step, DType::f32, {B, Din}, temb_.at());
  }
  dit_.forward(be, tokens_.at(), B, T, bucket, kv_, dit_masks_, dit_out_.at());
  if (dumping() && k == 0) dump_array<float>(be, "mid.dit_out.step0", DType::f32, {B, T, head_.hidden}, dit_out_.at());
  be.linear(*em.dec1, dit_out_.at(), B * T, dec_mid_.at());
  be.activate(dec_mid_.at(), B * T * head_.hidden, Activation::relu);
  be.linear(*em.dec2, dec_mid_.at(), B * T, dec_out_.at());
  if (dumping()) dump_array<float>(be, "mid.decoder_out." + step, DType::f32, {B, T, A}, dec_out_.at());
  for (int64_t b = 0; b < B; ++b) be.copy_rows(dec_out_.at((b * T + 1) * A), A, v + b * H * A, A, H, A);
}

ModelOutput Gr00tModel::predict(const std::vector<ModelInput>& batch) {
  ModelOutput out = begin_predict(batch);
  backend::Backend& be = *be_;
  const double flops_before = be.flops().total();
  const int64_t B = int64_t(batch.size()), D = head_.backbone_dim, Din = head_.input_dim;
  out.timings.set("preprocess", 0);

  // The backbone per observation, then one context of the longest prompt (shorter ones padded, the padding masked).
  std::vector<Prefix> prefixes;
  int64_t Lmax = 0;
  for (int64_t b = 0; b < B; ++b) {
    const Backbone bb = encode_backbone(batch[std::size_t(b)], b, out);
    // The VL layer norm and the VL self-attention (N1.7; none in N1.6) on this observation's features.
    const auto t0 = std::chrono::steady_clock::now();
    Prefix p;
    p.len = bb.len;
    p.image_mask = bb.image_mask;
    p.vl = be.alloc<float>(p.len * D);
    if (head_.use_vlln) be.layer_norm(bb.features, p.len, D, vlln_w_.at(), vlln_b_.at(), 1e-5f, p.vl.at());
    else be.copy_rows(bb.features, D, p.vl.at(), D, p.len, D);
    if (dumping()) dump_array<float>(be, "mid.vl_embeds.vlln", DType::f32, {1, p.len, D}, p.vl.at());
    vl_attention_.forward(be, p.vl.at(), 1, p.len);
    if (dumping()) dump_array<float>(be, "mid.vl_embeds", DType::f32, {1, p.len, D}, p.vl.at());
    be.synchronize();  // a GPU runs behind the host: time the work, not its queueing
    out.timings.set("backbone", out.timings.get("backbone") + elapsed_ms(t0));
    Lmax = std::max(Lmax, p.len);
    prefixes.push_back(std::move(p));
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

  // The state token: the state encoder's input (head_state), through the embodiment's state encoder.
  const Embodied& em = active();
  const int64_t S = head_.max_state_dim;
  std::vector<float> state(std::size_t(B * S), 0.f);
  for (int64_t b = 0; b < B; ++b) head_state(batch[std::size_t(b)], state.data() + b * S);
  if (dumping()) dump("pre.state", Tensor{DType::f32, {B, 1, S}, state.data(), nullptr});
  grow(be, state_, B * S);
  grow(be, state_mid_, B * head_.hidden);
  grow(be, state_tok_, B * Din);
  be.upload(state.data(), B * S, state_.at());
  be.linear(*em.state1, state_.at(), B, state_mid_.at());
  be.activate(state_mid_.at(), B * head_.hidden, Activation::relu);
  be.linear(*em.state2, state_mid_.at(), B, state_tok_.at());
  if (dumping()) dump_array<float>(be, "mid.state_features", DType::f32, {B, 1, Din}, state_tok_.at());
  be.synchronize();  // a GPU runs behind the host: time the work, not its queueing
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

namespace {

// One embodiment of a shared Gr00tModel, as the rest of Tether sees a model.
class Gr00tEmbodimentModel final : public Model {
 public:
  Gr00tEmbodimentModel(std::shared_ptr<Gr00tModel> model, std::size_t slot) : model_(std::move(model)), slot_(slot) {}
  const ModelSpec& spec() const override { return model_->spec_of(slot_); }
  ModelOutput predict(const std::vector<ModelInput>& batch) override {
    std::lock_guard lock(model_->mutex());
    model_->select(slot_);
    model_->set_debug_hook(debug_);
    return model_->predict(batch);
  }
  const Gr00tModel* shared() const { return model_.get(); }

 private:
  std::shared_ptr<Gr00tModel> model_;
  std::size_t slot_;
};

// The loaded checkpoints, by what decides their shared part: the directory, the precision and the backend (held by
// the model, so its address stays unique while the entry can be used). The config is compared too: a directory
// rewritten in place is loaded anew.
struct SharedKey {
  std::string dir;
  int precision;
  const backend::Backend* backend;
  auto operator<=>(const SharedKey&) const = default;
};
struct SharedEntry {
  std::weak_ptr<Gr00tModel> model;
  Json config;
};
std::mutex shared_models_mutex;
std::map<SharedKey, SharedEntry> shared_models;

}  // namespace

std::unique_ptr<Model> load_gr00t_embodiment(const fs::path& dir, const Json& config, TensorStore store,
                                             const LoadOptions& options,
                                             const std::function<std::unique_ptr<Gr00tModel>(TensorStore)>& make) {
  std::error_code ec;
  const fs::path canonical = fs::weakly_canonical(dir, ec);
  const SharedKey key{(ec ? dir : canonical).string(), int(options.precision), options.backend.get()};
  // Held for the whole load: a second embodiment of a checkpoint being loaded waits for it rather than loading twice.
  std::lock_guard registry(shared_models_mutex);
  for (auto it = shared_models.begin(); it != shared_models.end();)  // entries whose models are gone
    it = it->second.model.expired() ? shared_models.erase(it) : std::next(it);
  auto it = shared_models.find(key);
  if (it != shared_models.end() && it->second.config == config) {
    std::shared_ptr<Gr00tModel> model = it->second.model.lock();
    std::lock_guard lock(model->mutex());
    Weights w(std::move(store));  // only this embodiment's category rows are read from it
    const std::size_t slot = model->add_embodiment(dir, options.embodiment, w);
    return std::make_unique<Gr00tEmbodimentModel>(std::move(model), slot);
  }
  std::shared_ptr<Gr00tModel> model = make(std::move(store));
  shared_models[key] = {model, config};
  return std::make_unique<Gr00tEmbodimentModel>(std::move(model), 0);
}

bool gr00t_shares_weights(const Model& a, const Model& b) {
  const auto* x = dynamic_cast<const Gr00tEmbodimentModel*>(&a);
  const auto* y = dynamic_cast<const Gr00tEmbodimentModel*>(&b);
  return x && y && x->shared() == y->shared();
}

}  // namespace tether::models
