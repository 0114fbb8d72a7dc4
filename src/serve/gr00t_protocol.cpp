// GR00T's ZMQ protocol: decoding requests and encoding replies (no sockets here).
#include "serve/gr00t_protocol.h"

#include <cmath>

#include "serve/http_error.h"
#include "serve/msgpack_json.h"
#include "serve/ndarray.h"

namespace tether::serve::gr00t {

namespace {

[[noreturn]] void fail(const std::string& code, const std::string& message) { throw HttpError(400, code, message); }

std::string kind_of(const msgpack::Value& v) { return msgpack::kind_name(v.kind); }

bool starts_with(std::string_view s, std::string_view p) { return s.substr(0, p.size()) == p; }

// An {"__ndarray_class__": true, "as_npy": bin} map as an array; `field` names it in errors.
NdArray ndarray(const msgpack::Value& v, const std::string& field) {
  const msgpack::Value* tag = v.is_map() ? v.find("__ndarray_class__") : nullptr;
  const msgpack::Value* npy = v.is_map() ? v.find("as_npy") : nullptr;
  if (!tag || !npy)
    fail("invalid_field", field + ": expected a numpy array ({\"__ndarray_class__\": true, \"as_npy\": <npy bytes>}), got " +
                              (v.is_map() ? std::string("a map without them") : kind_of(v)));
  if (!npy->is_text_or_bin()) fail("invalid_field", field + ".as_npy: expected bytes, got " + kind_of(*npy));
  try {
    return parse_npy(npy->bytes);
  } catch (const ArrayError& e) {
    fail("invalid_field", field + ": " + e.what());
  }
}

struct Fields {
  std::vector<std::pair<std::string, const msgpack::Value*>> video, state;
  const msgpack::Value* language = nullptr;
  std::string language_field;
};

const msgpack::Value* observation_of(const Call& call) {
  if (!call.data.is_map()) fail("missing_field", "data: get_action needs {\"observation\": {...}}");
  const msgpack::Value* obs = call.data.find("observation");
  if (!obs || obs->is_nil()) fail("missing_field", "data.observation is required");
  if (!obs->is_map()) fail("invalid_field", "data.observation: expected a map, got " + kind_of(*obs));
  return obs;
}

bool is_nested(const msgpack::Value& obs) {
  for (const char* k : {"video", "state", "language"}) {
    const msgpack::Value* v = obs.find(k);
    if (v && v->is_map()) return true;
  }
  return false;
}

std::string key_text(const msgpack::Value& k, const std::string& where) {
  if (!k.is_text_or_bin()) fail("invalid_field", where + ": keys must be strings, got " + kind_of(k));
  return std::string(k.bytes);
}

Fields fields_of(const msgpack::Value& obs) {
  Fields f;
  if (is_nested(obs)) {
    for (const auto& [k, v] : obs.entries) {
      const std::string key = key_text(k, "observation");
      if (key != "video" && key != "state" && key != "language")
        fail("unknown_field", "observation." + key + ": unknown modality (accepted: video, state, language)");
      if (!v.is_map()) fail("invalid_field", "observation." + key + ": expected a map, got " + kind_of(v));
      if (key == "language") {
        for (const auto& [lk, lv] : v.entries) {
          const std::string name = key_text(lk, "observation.language");
          if (f.language) fail("invalid_field", "observation.language: one instruction key is supported, got another: " + name);
          f.language = &lv;
          f.language_field = "observation.language." + name;
        }
        continue;
      }
      auto& out = key == "video" ? f.video : f.state;
      for (const auto& [gk, gv] : v.entries) out.emplace_back(key_text(gk, "observation." + key), &gv);
    }
    return f;
  }
  for (const auto& [k, v] : obs.entries) {
    const std::string key = key_text(k, "observation");
    if (starts_with(key, "video.")) {
      f.video.emplace_back(key.substr(6), &v);
    } else if (starts_with(key, "state.")) {
      f.state.emplace_back(key.substr(6), &v);
    } else if (key == "task" || key == "language.task" || key == "annotation.human.coarse_action" ||
               starts_with(key, "annotation.") || starts_with(key, "language.")) {
      if (f.language) fail("invalid_field", "observation: one instruction key is supported, got '" + f.language_field.substr(12) + "' and '" + key + "'");
      f.language = &v;
      f.language_field = "observation." + key;
    } else {
      fail("unknown_field", "observation." + key + ": unknown key (accepted: video.<camera>, state.<group>, task)");
    }
  }
  return f;
}

std::string video_field(const std::string& name) { return "observation.video." + name; }

// The instruction of item `index`: [[str]] (B, T: the last), [str] (B), or one str for every item.
std::string instruction_of(const msgpack::Value& v, int64_t index, int64_t batch, const std::string& field) {
  if (v.is_str()) return std::string(v.bytes);
  if (!v.is_array()) fail("invalid_field", field + ": expected a list of strings, one per batch item, got " + kind_of(v));
  if (int64_t(v.items.size()) != batch)
    fail("invalid_field", field + ": " + std::to_string(v.items.size()) + " items for a batch of " + std::to_string(batch));
  const msgpack::Value& item = v.items[std::size_t(index)];
  const std::string where = field + "[" + std::to_string(index) + "]";
  if (item.is_str()) return std::string(item.bytes);
  if (item.is_array() && !item.items.empty() && item.items.back().is_str()) return std::string(item.items.back().bytes);
  fail("invalid_field", where + ": expected a string or a list of strings, got " + kind_of(item));
}

// options.<name>: one value for every item, or a list with one per item; null when absent.
const msgpack::Value* option(const Call& call, const char* name, int64_t index, int64_t batch) {
  const msgpack::Value* options = call.data.is_map() ? call.data.find("options") : nullptr;
  if (!options || options->is_nil()) return nullptr;
  if (!options->is_map()) fail("invalid_field", "data.options: expected a map or null, got " + kind_of(*options));
  const msgpack::Value* v = options->find(name);
  if (!v || v->is_nil()) return nullptr;
  if (!v->is_array()) return v;
  if (int64_t(v->items.size()) != batch)
    fail("invalid_field", std::string("data.options.") + name + ": " + std::to_string(v->items.size()) +
                              " values for a batch of " + std::to_string(batch));
  return &v->items[std::size_t(index)];
}

// "'a' (3 values), 'b' (2 values)", for errors.
std::string groups_text(const std::vector<models::ModalityGroup>& groups) {
  std::string out;
  for (const auto& g : groups)
    out += (out.empty() ? "'" : ", '") + g.name + "' (" + std::to_string(g.dim) + " values)";
  return out;
}

// The group a wire name stands for, or groups.size(). A model with one state group also takes it under its feature
// key ("observation.state").
std::size_t group_index(const std::vector<models::ModalityGroup>& groups, const std::string& name,
                        const models::ModelSpec& spec) {
  for (std::size_t g = 0; g < groups.size(); ++g)
    if (groups[g].name == name) return g;
  if (groups.size() == 1 && !spec.state_key.empty() && name == spec.state_key) return 0;
  return groups.size();
}

// A ModalityConfig as Isaac-GR00T's client decodes it: {"__ModalityConfig_class__": true, "as_json": {its five
// fields}}. The keys and steps are what this server takes and answers; the encoding fields (sin_cos_embedding_keys,
// mean_std_embedding_keys, action_configs) are the checkpoint's own (`own`: its modality config) where its keys are
// the same, else null.
void write_modality(msgpack::Writer& w, const Json& own, const char* modality, const std::vector<int64_t>& delta,
                    const std::vector<std::string>& keys) {
  Json as_json = {{"delta_indices", delta}, {"modality_keys", keys}};
  const Json* checkpoint = own.is_object() && own.contains(modality) ? &own.at(modality) : nullptr;
  const bool described = checkpoint && checkpoint->is_object() &&
                         checkpoint->value("modality_keys", Json()) == as_json.at("modality_keys");
  for (const char* k : {"sin_cos_embedding_keys", "mean_std_embedding_keys", "action_configs"})
    as_json[k] = described ? checkpoint->value(k, Json()) : Json();
  w.map(2);
  w.str("__ModalityConfig_class__");
  w.boolean(true);
  w.str("as_json");
  msgpack::write_json(w, as_json);
}

// The instruction's key: the checkpoint's language key (any key is accepted as the instruction), else "task".
std::vector<std::string> language_keys(const models::ModelSpec& spec) {
  const Json& own = spec.modality_config;
  if (own.is_object() && own.contains("language") && own.at("language").is_object()) {
    const Json keys = own.at("language").value("modality_keys", Json());
    if (keys.is_array() && keys.size() == 1 && keys.front().is_string()) return {keys.front().get<std::string>()};
  }
  return {"task"};
}

}  // namespace

Call parse_call(std::string_view message) {
  msgpack::Value root = msgpack::parse_map(message, "message", "{endpoint, data, api_token}");
  Call call;
  std::string endpoint = "get_action";
  for (auto& [k, v] : root.entries) {
    if (!k.is_text_or_bin()) continue;
    if (k.bytes == "endpoint") {
      if (!v.is_text_or_bin()) fail("invalid_field", "endpoint: expected a string, got " + kind_of(v));
      endpoint = std::string(v.bytes);
    } else if (k.bytes == "api_token") {
      if (v.is_nil()) continue;
      if (!v.is_text_or_bin()) fail("invalid_field", "api_token: expected a string, got " + kind_of(v));
      call.api_token = std::string(v.bytes);
    } else if (k.bytes == "data") {
      call.data = std::move(v);
    }
  }
  if (endpoint == "ping") call.endpoint = Endpoint::ping;
  else if (endpoint == "kill") call.endpoint = Endpoint::kill;
  else if (endpoint == "get_action") call.endpoint = Endpoint::get_action;
  else if (endpoint == "reset") call.endpoint = Endpoint::reset;
  else if (endpoint == "get_modality_config") call.endpoint = Endpoint::get_modality_config;
  else fail("unknown_endpoint", "Unknown endpoint: " + endpoint.substr(0, 64));
  return call;
}

Layout observation_layout(const Call& call) {
  Layout layout;
  try {
    const msgpack::Value* obs = observation_of(call);
    layout.flat = !is_nested(*obs);
    const Fields f = fields_of(*obs);
    if (f.video.empty() && f.state.empty()) return layout;
    const msgpack::Value* first = !f.video.empty() ? f.video.front().second : f.state.front().second;
    const NdArray a = ndarray(*first, "observation");
    if (!a.shape.empty() && a.shape[0] >= 1) layout.batch = a.shape[0];
  } catch (const HttpError&) {
  }
  return layout;
}

ActRequest decode_item(const Call& call, int64_t index, const models::ModelSpec& spec) {
  const msgpack::Value* obs = observation_of(call);
  const bool flat = !is_nested(*obs);
  const Fields f = fields_of(*obs);
  int64_t batch = -1;
  auto check_batch = [&](const NdArray& a, const std::string& field) {
    if (a.shape.empty() || a.shape[0] < 1) fail("invalid_field", field + ": the first dimension is the batch, got an empty one");
    if (batch < 0) batch = a.shape[0];
    else if (a.shape[0] != batch)
      fail("invalid_field", field + ": batch size " + std::to_string(a.shape[0]) + ", other arrays have " + std::to_string(batch));
  };
  ActRequest req;
  policy::Observation& o = req.observation;
  for (const auto& [name, v] : f.video) {
    const std::string field = video_field(name);
    const auto camera = resolve_camera(name, spec);
    if (!camera) {
      std::string known;
      for (const auto& c : spec.cameras) known += (known.empty() ? "" : ", ") + camera_name(c, spec);
      fail("unknown_camera", field + ": the model has no camera '" + name + "' (it has: " + known + ")");
    }
    const NdArray a = ndarray(*v, field);
    if (a.dtype != DType::u8) fail("invalid_field", field + ": expected uint8 pixels, got " + dtype_name(a.dtype));
    if (a.shape.size() != 5 && a.shape.size() != 4)
      fail("invalid_field", field + ": expected shape (B, T, H, W, 3) or (B, H, W, 3), got " + std::to_string(a.shape.size()) + " dimensions");
    if (a.shape.back() != 3) fail("invalid_field", field + ": expected 3 channels (RGB), got " + std::to_string(a.shape.back()));
    check_batch(a, field);
    const int64_t frames = a.shape.size() == 5 ? a.shape[1] : 1;
    const int64_t h = a.shape[a.shape.size() - 3], w = a.shape[a.shape.size() - 2];
    if (frames < 1 || h < 1 || w < 1) fail("invalid_field", field + ": an empty image");
    if (index >= batch) fail("invalid_field", field + ": no batch item " + std::to_string(index));
    if (o.images.count(*camera)) fail("invalid_field", field + ": camera '" + *camera + "' is given twice");
    // T > 1 (a history of frames): the model takes one frame per camera, the latest.
    const std::size_t frame_bytes = std::size_t(h) * std::size_t(w) * 3;
    const std::size_t offset = (std::size_t(index) * std::size_t(frames) + std::size_t(frames - 1)) * frame_bytes;
    o.images[*camera] = raw_rgb_image(reinterpret_cast<const uint8_t*>(a.data.data()) + offset, h, w, field);
  }
  // The state groups are concatenated in the spec's order, each one checked for its own size.
  const std::vector<models::ModalityGroup> groups = models::state_groups(spec);
  std::vector<const std::pair<std::string, const msgpack::Value*>*> given(groups.size(), nullptr);
  for (const auto& entry : f.state) {
    const std::size_t g = group_index(groups, entry.first, spec);
    if (g == groups.size())
      fail("unknown_field", "observation.state." + entry.first + ": unknown state group (the model has: " +
                                groups_text(groups) + ")");
    if (given[g])
      fail("invalid_field",
           "observation.state." + entry.first + ": state group '" + groups[g].name + "' is given twice");
    given[g] = &entry;
  }
  for (std::size_t g = 0; g < groups.size(); ++g) {
    if (given[g]) continue;
    const std::string listing = groups.size() > 1 ? "; the model's state groups: " + groups_text(groups) : "";
    fail("missing_field", "observation.state." + groups[g].name + " is required (" + std::to_string(groups[g].dim) +
                              " values" + listing + ")");
  }
  for (std::size_t g = 0; g < groups.size(); ++g) {
    const auto& [name, v] = *given[g];
    const std::string field = "observation.state." + name;
    const NdArray a = ndarray(*v, field);
    if (a.dtype == DType::boolean) fail("invalid_field", field + ": expected float32 values, got bool");
    if (a.shape.size() != 3 && a.shape.size() != 2)
      fail("invalid_field", field + ": expected shape (B, T, D) or (B, D), got " + std::to_string(a.shape.size()) + " dimensions");
    check_batch(a, field);
    const int64_t steps = a.shape.size() == 3 ? a.shape[1] : 1;
    const int64_t dim = a.shape.back();
    if (steps < 1) fail("invalid_field", field + ": no time step");
    if (dim != groups[g].dim)
      fail("invalid_state", field + " has " + std::to_string(dim) + " values, the model expects " +
                                std::to_string(groups[g].dim));
    if (index >= batch) fail("invalid_field", field + ": no batch item " + std::to_string(index));
    std::vector<float> all;
    try {
      all = to_float32(a);
    } catch (const ArrayError& e) {
      fail("invalid_field", field + ": " + e.what());
    }
    const std::size_t start = (std::size_t(index) * std::size_t(steps) + std::size_t(steps - 1)) * std::size_t(dim);
    const auto from = all.begin() + std::ptrdiff_t(start);
    o.state.insert(o.state.end(), from, from + std::ptrdiff_t(dim));
  }
  if (batch < 1) batch = 1;
  if (!f.language) fail("missing_field", flat ? "observation.task is required (the instruction, one per batch item)"
                                              : "observation.language.task is required (the instruction, [[str]] per batch item)");
  o.instruction = instruction_of(*f.language, index, batch, f.language_field);
  if (const msgpack::Value* seed = option(call, "seed", index, batch)) {
    if (seed->kind != msgpack::Kind::integer || (!seed->above_int64 && seed->integer < 0))
      fail("invalid_field", "data.options.seed: expected an integer >= 0");
    req.seed = seed->above_int64 ? seed->uinteger : uint64_t(seed->integer);
  }
  if (const msgpack::Value* ep = option(call, "episode_id", index, batch)) {
    if (!ep->is_str()) fail("invalid_field", "data.options.episode_id: expected a string, got " + kind_of(*ep));
    req.episode_id = std::string(ep->bytes);
  }
  const std::string tag = call_embodiment(call);
  if (!tag.empty() && tag != spec.embodiment)  // the pipeline routed the call by it: a bug if they differ
    fail("invalid_field", "data.options.embodiment_tag: '" + tag + "' is not the embodiment '" + spec.embodiment +
                              "' this call was decoded for");
  req.embodiment = tag;
  check_observation(o, spec);
  return req;
}

std::string camera_name(const std::string& key, const models::ModelSpec& spec) {
  if (!spec.camera_prefix.empty() && starts_with(key, spec.camera_prefix)) return key.substr(spec.camera_prefix.size());
  return key;
}

std::string ping_reply() {
  msgpack::Writer w;
  w.map(2);
  w.str("status");
  w.str("ok");
  w.str("message");
  w.str("Server is running");
  return w.take();
}

std::string reset_reply() {
  msgpack::Writer w;
  w.map(0);
  return w.take();
}

std::string kill_reply() {
  msgpack::Writer w;
  w.nil();
  return w.take();
}

std::string error_reply(int status, const std::string& code, const std::string& message) {
  msgpack::Writer w;
  w.map(3);
  w.str("error");
  // Upstream's own wording for a bad token, which its client shows as "Server error: ...".
  w.str(status == 401 ? "Unauthorized: Invalid API token (" + message + ")" : message);
  w.str("code");
  w.str(code);
  w.str("status");
  w.integer(status);
  return w.take();
}

std::string modality_config_reply(const models::ModelSpec& spec, int64_t action_dim) {
  std::vector<std::string> cameras;
  for (const auto& c : spec.cameras) cameras.push_back(camera_name(c, spec));
  std::vector<int64_t> horizon;
  for (int64_t i = 0; i < spec.chunk_size; ++i) horizon.push_back(i);
  msgpack::Writer w;
  w.map(5);
  w.str("video");
  write_modality(w, spec.modality_config, "video", {0}, cameras);
  const auto state = models::state_groups(spec);
  const auto action = models::answered_action_groups(spec, action_dim);
  const auto names = [](const std::vector<models::ModalityGroup>& groups) {
    std::vector<std::string> out;
    for (const auto& g : groups) out.push_back(g.name);
    return out;
  };
  w.str("state");
  write_modality(w, spec.modality_config, "state", {0}, names(state));
  w.str("action");
  write_modality(w, spec.modality_config, "action", horizon, names(action));
  w.str("language");
  write_modality(w, spec.modality_config, "language", {0}, language_keys(spec));
  Json tether = {{"family", spec.family},
                 {"cameras", cameras},
                 {"camera_keys", spec.cameras},
                 {"state_dim", spec.state_dim},
                 {"action_dim", action_dim},
                 {"state_groups", models::groups_json(state)},
                 {"action_groups", models::groups_json(action)},
                 {"chunk_size", spec.chunk_size},
                 {"image_height", spec.image_height},
                 {"image_width", spec.image_width}};
  w.str("tether");
  msgpack::write_json(w, tether);
  return w.take();
}

void write_ndarray(msgpack::Writer& w, const std::string& npy) {
  w.map(2);
  w.str("__ndarray_class__");
  w.boolean(true);
  w.str("as_npy");
  w.bin(npy);
}

std::string call_embodiment(const Call& call) {
  const msgpack::Value* options = call.data.is_map() ? call.data.find("options") : nullptr;
  if (!options || !options->is_map()) return "";
  const msgpack::Value* tag = options->find("embodiment_tag");
  if (!tag || tag->is_nil()) return "";
  if (!tag->is_str()) fail("invalid_field", "data.options.embodiment_tag: expected a string, got " + kind_of(*tag));
  return std::string(tag->bytes);
}

std::vector<std::string> reset_episodes(const Call& call) {
  if (!call.data.is_nil() && !call.data.is_map())
    fail("invalid_field", "data: expected a map or null, got " + kind_of(call.data));
  const msgpack::Value* options = call.data.is_map() ? call.data.find("options") : nullptr;
  if (options && !options->is_nil() && !options->is_map())
    fail("invalid_field", "data.options: expected a map or null, got " + kind_of(*options));
  const msgpack::Value* id = options && options->is_map() ? options->find("episode_id") : nullptr;
  if (!id || id->is_nil()) return {""};
  if (id->is_str()) return {std::string(id->bytes)};
  if (!id->is_array())
    fail("invalid_field", "data.options.episode_id: expected a string or a list of strings, got " + kind_of(*id));
  std::vector<std::string> ids;
  for (std::size_t i = 0; i < id->items.size(); ++i) {
    const msgpack::Value& item = id->items[i];
    if (!item.is_str())
      fail("invalid_field",
           "data.options.episode_id[" + std::to_string(i) + "]: expected a string, got " + kind_of(item));
    ids.emplace_back(item.bytes);
  }
  return ids;
}

std::string action_reply(const std::vector<models::ModalityGroup>& groups, bool flat, int64_t batch, int64_t rows,
                         int64_t dim, const std::vector<float>& actions, const Json& items) {
  int64_t total = 0;
  for (const auto& g : groups) total += g.dim;
  if (total != dim)
    return error_reply(500, "internal_error", "the answer has " + std::to_string(dim) +
                                                  " action values per step, the action groups add up to " +
                                                  std::to_string(total));
  msgpack::Writer w;
  w.array(2);
  w.map(uint32_t(groups.size()));
  int64_t column = 0;
  std::vector<float> part;
  for (const auto& g : groups) {
    // Group g's columns of every (item, row).
    part.clear();
    part.reserve(std::size_t(batch * rows * g.dim));
    for (int64_t r = 0; r < batch * rows; ++r) {
      const auto from = actions.begin() + std::ptrdiff_t(r * dim + column);
      part.insert(part.end(), from, from + std::ptrdiff_t(g.dim));
    }
    column += g.dim;
    w.str(flat ? "action." + g.name : g.name);
    const std::string_view bytes(reinterpret_cast<const char*>(part.data()), part.size() * sizeof(float));
    write_ndarray(w, write_npy(DType::f32, {batch, rows, g.dim}, bytes));
  }
  w.map(1);
  w.str("tether");
  msgpack::write_json(w, items);
  return w.take();
}

}  // namespace tether::serve::gr00t
