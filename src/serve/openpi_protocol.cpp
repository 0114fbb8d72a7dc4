// Decoding openpi observation frames through a key layout, and encoding openpi's reply and metadata maps.
#include "serve/openpi_protocol.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <fstream>
#include <limits>
#include <sstream>

#include "serve/http_error.h"
#include "serve/msgpack.h"
#include "serve/ndarray.h"

namespace tether::serve::openpi {

namespace {

[[noreturn]] void fail(const std::string& code, const std::string& message) { throw HttpError(400, code, message); }

std::string join(const std::vector<std::string>& items) {
  std::string out;
  for (const auto& s : items) out += (out.empty() ? "" : ", ") + s;
  return out;
}

// The keys a layout reads, in a stable order, for error messages.
std::vector<std::string> known_keys(const Layout& layout) {
  std::vector<std::string> keys;
  for (const auto& img : layout.images) keys.push_back(img.key);
  keys.insert(keys.end(), layout.state.begin(), layout.state.end());
  keys.push_back(layout.prompt);
  keys.insert(keys.end(), layout.ignored.begin(), layout.ignored.end());
  return keys;
}

bool reads_key(const Layout& layout, const std::string& key) {
  if (key == kEpisodeKey || key == kSeedKey) return true;
  const auto keys = known_keys(layout);
  return std::find(keys.begin(), keys.end(), key) != keys.end();
}

// --- msgpack-numpy values ---------------------------------------------------------------------------------------

bool is_ndarray(const msgpack::Value& v) { return v.is_map() && v.find("__ndarray__"); }
bool is_npgeneric(const msgpack::Value& v) { return v.is_map() && v.find("__npgeneric__"); }

std::string shape_text(const std::vector<int64_t>& shape) {
  std::string s = "[";
  for (std::size_t i = 0; i < shape.size(); ++i) s += (i ? ", " : "") + std::to_string(shape[i]);
  return s + "]";
}

DType dtype_of(const msgpack::Value& map, const std::string& key) {
  const msgpack::Value* dtype = map.find("dtype");
  if (!dtype || !dtype->is_text_or_bin()) fail("invalid_field", key + ": 'dtype' must be a string such as '<f4'");
  try {
    return parse_dtype(dtype->bytes);
  } catch (const ArrayError& e) {
    fail("invalid_field", key + ": " + e.what());
  }
}

NdArray ndarray_of(const msgpack::Value& map, const std::string& key) {
  const msgpack::Value* data = map.find("data");
  const msgpack::Value* shape = map.find("shape");
  if (!data || !data->is_text_or_bin()) fail("invalid_field", key + ": an __ndarray__ needs 'data' (bytes)");
  if (!shape || !shape->is_array()) fail("invalid_field", key + ": an __ndarray__ needs 'shape' (a list of integers)");
  const DType dtype = dtype_of(map, key);
  std::vector<int64_t> dims;
  for (const auto& d : shape->items) {
    if (d.kind != msgpack::Kind::integer || d.above_int64 || d.integer < 0)
      fail("invalid_field", key + ": 'shape' must hold non-negative integers");
    dims.push_back(d.integer);
  }
  try {
    return make_array(dtype, std::move(dims), data->bytes);
  } catch (const ArrayError& e) {
    fail("invalid_field", key + ": " + e.what());
  }
}

// A numpy scalar (np.float64(0.5)): its value as a double. Bools and integers are numbers here too.
double npgeneric_number(const msgpack::Value& map, const std::string& key) {
  const msgpack::Value* data = map.find("data");
  dtype_of(map, key);  // refuses object and unknown dtypes
  if (!data) fail("invalid_field", key + ": an __npgeneric__ needs 'data'");
  if (data->kind == msgpack::Kind::boolean) return data->boolean ? 1 : 0;
  if (!data->is_number()) fail("invalid_field", key + ": expected a number, got " + msgpack::kind_name(data->kind));
  return data->as_double();
}

// Numbers as float32, refusing what float32 cannot hold (non-finite values are left to check_observation).
float to_float(double v, const std::string& key) {
  if (std::isfinite(v) && std::fabs(v) > double(std::numeric_limits<float>::max()))
    fail("invalid_state", key + ": value " + std::to_string(v) + " does not fit in float32");
  return float(v);
}

void append_state(const msgpack::Value& v, const std::string& key, std::vector<float>& state) {
  if (is_ndarray(v)) {
    const NdArray a = ndarray_of(v, key);
    if (a.shape.size() > 1)
      fail("invalid_state", key + ": expected a vector or a scalar, got shape " + shape_text(a.shape));
    try {
      const auto values = to_float32(a);
      state.insert(state.end(), values.begin(), values.end());
    } catch (const ArrayError& e) {
      fail("invalid_state", key + ": " + e.what());
    }
  } else if (is_npgeneric(v)) {
    state.push_back(to_float(npgeneric_number(v, key), key));
  } else if (v.is_number()) {
    state.push_back(to_float(v.as_double(), key));
  } else if (v.is_array()) {  // a plain list of numbers
    for (std::size_t i = 0; i < v.items.size(); ++i) {
      if (!v.items[i].is_number())
        fail("invalid_state", key + "[" + std::to_string(i) + "]: expected a number, got " +
                                  msgpack::kind_name(v.items[i].kind));
      state.push_back(to_float(v.items[i].as_double(), key));
    }
  } else {
    fail("invalid_state", key + ": expected an array of numbers, got " + std::string(msgpack::kind_name(v.kind)));
  }
}

template <typename T>
T load(const char* p) {
  T v;
  std::memcpy(&v, p, sizeof v);
  return v;
}

// Element i of a float image as a pixel, as openpi's (255 * image).astype(np.uint8): scaled in the array's own
// precision, then truncated. Values outside [0, 1] are refused (numpy's cast would wrap them).
uint8_t float_pixel(const NdArray& a, std::size_t i, const std::string& key) {
  const char* p = a.data.data() + i * dtype_size(a.dtype);
  double v = 0, scaled = 0;
  if (a.dtype == DType::f64) {
    v = load<double>(p);
    scaled = 255.0 * v;
  } else {
    const float f = a.dtype == DType::f32 ? load<float>(p) : half_to_float(load<uint16_t>(p));
    v = f;
    scaled = double(255.0f * f);
  }
  if (!(v >= 0 && v <= 1))
    fail("invalid_image", key + ": a float image must hold values in [0, 1] (scaled by 255), found " +
                              std::to_string(v) + " at element " + std::to_string(i));
  return uint8_t(scaled);
}

// An image array: uint8 or float in [0, 1], [H, W, 3] or [3, H, W] (taken as channels-first whenever its first
// dimension is 3, as openpi's image parsing does).
vision::Image decode_image(const msgpack::Value& v, const std::string& key) {
  if (!is_ndarray(v))
    fail("invalid_image", key + ": expected an image array (msgpack-numpy __ndarray__), got " +
                              std::string(is_npgeneric(v) ? "a numpy scalar" : msgpack::kind_name(v.kind)));
  const NdArray a = ndarray_of(v, key);
  const bool is_float = a.dtype == DType::f16 || a.dtype == DType::f32 || a.dtype == DType::f64;
  if (a.dtype != DType::u8 && !is_float)
    fail("invalid_image", key + ": expected uint8 pixels (or float in [0, 1]), got " + dtype_name(a.dtype));
  if (a.shape.size() != 3 || (a.shape[0] != 3 && a.shape[2] != 3))
    fail("invalid_image", key + ": expected shape [H, W, 3] or [3, H, W], got " + shape_text(a.shape));
  const bool chw = a.shape[0] == 3;
  const int64_t height = chw ? a.shape[1] : a.shape[0], width = chw ? a.shape[2] : a.shape[1];
  if (height < 1 || width < 1) fail("invalid_image", key + ": an image needs at least one pixel");
  if (!chw && !is_float) return raw_rgb_image(reinterpret_cast<const uint8_t*>(a.data.data()), height, width, key);
  const std::size_t plane = std::size_t(height) * std::size_t(width);
  std::vector<uint8_t> hwc(plane * 3);
  const auto* bytes = reinterpret_cast<const uint8_t*>(a.data.data());
  for (std::size_t c = 0; c < 3; ++c)
    for (std::size_t px = 0; px < plane; ++px) {
      const std::size_t src = chw ? c * plane + px : px * 3 + c;
      hwc[px * 3 + c] = is_float ? float_pixel(a, src, key) : bytes[src];
    }
  return raw_rgb_image(hwc.data(), height, width, key);
}

std::string decode_text(const msgpack::Value& v, const std::string& key) {
  const msgpack::Value* text = &v;
  if (is_npgeneric(v)) text = v.find("data");  // np.str_: its data is the string
  if (!text || !text->is_text_or_bin())
    fail("invalid_field", key + ": expected a string, got " + std::string(msgpack::kind_name(v.kind)));
  return std::string(text->bytes);
}

// --- the frame's keys --------------------------------------------------------------------------------------------

struct Leaf {
  std::string key;
  const msgpack::Value* value;
};

// An observation has a handful of keys; the cap keeps the key checks below cheap on hostile frames.
constexpr std::size_t kMaxKeys = 256;
// Pixels travel as binaries, so a frame needs few msgpack elements (keys, shapes, a state list); each parsed element
// costs about a hundred bytes, so the default million would let one 1 MiB frame take 100 MiB.
constexpr msgpack::Limits kFrameLimits{16, 1 << 14};

// Nested maps that are not arrays become '/'-joined keys.
void flatten(const msgpack::Value& map, const std::string& prefix, std::vector<Leaf>& out) {
  for (const auto& [k, v] : map.entries) {
    if (!k.is_text_or_bin())
      fail("invalid_field", (prefix.empty() ? "the frame" : prefix) + ": keys must be strings, got " +
                                msgpack::kind_name(k.kind));
    const std::string key = prefix.empty() ? std::string(k.bytes) : prefix + "/" + std::string(k.bytes);
    if (v.is_map() && !is_ndarray(v) && !is_npgeneric(v)) {
      flatten(v, key, out);
      continue;
    }
    if (out.size() >= kMaxKeys) fail("invalid_field", "the frame has more than " + std::to_string(kMaxKeys) + " keys");
    for (const auto& seen : out)
      if (seen.key == key) fail("invalid_field", "key '" + key + "' appears twice");
    out.push_back({key, &v});
  }
}

const Layout& choose_layout(const Layouts& layouts, const std::vector<Leaf>& leaves) {
  if (layouts.candidates.empty()) throw Error(ErrorCode::internal, "openpi: no layout configured");
  const Layout* best = &layouts.candidates.front();
  std::size_t best_known = 0;
  for (const auto& layout : layouts.candidates) {
    std::size_t known = 0;
    for (const auto& leaf : leaves) known += reads_key(layout, leaf.key);
    if (known == leaves.size()) return layout;
    if (known > best_known) best = &layout, best_known = known;
  }
  return *best;
}

const msgpack::Value* find_leaf(const std::vector<Leaf>& leaves, const std::string& key) {
  for (const auto& leaf : leaves)
    if (leaf.key == key) return leaf.value;
  return nullptr;
}

std::vector<std::string> client_cameras(const models::ModelSpec& spec) {
  std::vector<std::string> out;
  for (const auto& c : spec.cameras)
    if (std::find(spec.synthetic_cameras.begin(), spec.synthetic_cameras.end(), c) == spec.synthetic_cameras.end())
      out.push_back(c);
  return out;
}

// --- the mapping file ------------------------------------------------------------------------------------------

std::string checked_string(const Json& j, const std::string& where) {
  if (!j.is_string() || j.get_ref<const std::string&>().empty())
    throw Error(ErrorCode::invalid_argument, where + ": expected a non-empty string, got " + j.dump());
  return j.get<std::string>();
}

Layout libero() {
  Layout l;
  l.name = "libero";
  l.images = {{"observation/image", "image"}, {"observation/wrist_image", "wrist_image"}};
  l.fill_by_position = true;
  l.state = {"observation/state"};
  return l;
}

Layout droid() {
  Layout l;
  l.name = "droid";
  l.images = {{"observation/exterior_image_1_left", "exterior_image_1_left"},
              {"observation/wrist_image_left", "wrist_image_left"}};
  l.fill_by_position = true;
  l.state = {"observation/joint_position", "observation/gripper_position"};
  return l;
}

Layout aloha() {
  Layout l;
  l.name = "aloha";
  // openpi's order: the base view, then the left and right wrists; cam_low last (pi0's aloha inputs drop it).
  l.images = {{"images/cam_high", "cam_high"},
              {"images/cam_left_wrist", "cam_left_wrist"},
              {"images/cam_right_wrist", "cam_right_wrist"},
              {"images/cam_low", "cam_low"}};
  l.fill_by_position = true;
  l.state = {"state"};
  return l;
}

}  // namespace

std::vector<Layout> builtin_layouts() { return {libero(), droid(), aloha()}; }

Layout parse_layout_json(std::string_view text, const std::string& source) {
  Json j;
  try {
    j = Json::parse(text);
  } catch (const std::exception& e) {
    throw Error(ErrorCode::invalid_argument, source + ": not valid JSON: " + e.what());
  }
  if (!j.is_object()) throw Error(ErrorCode::invalid_argument, source + ": expected a JSON object");
  static const char* const kKeys[] = {"images", "state", "prompt", "default_prompt", "ignore"};
  for (auto it = j.begin(); it != j.end(); ++it)
    if (std::find_if(std::begin(kKeys), std::end(kKeys), [&](const char* k) { return it.key() == k; }) == std::end(kKeys))
      throw Error(ErrorCode::invalid_argument,
                  source + ": unknown key '" + it.key() + "' (expected: images, state, prompt, default_prompt, ignore)");
  Layout l;
  l.name = source;
  const auto images = j.find("images");
  if (images == j.end() || !images->is_object() || images->empty())
    throw Error(ErrorCode::invalid_argument, source + ": 'images' must map client keys to camera names");
  for (auto it = images->begin(); it != images->end(); ++it)
    l.images.push_back({it.key(), checked_string(it.value(), source + ": images." + it.key())});
  const auto state = j.find("state");
  if (state == j.end() || !(state->is_string() || (state->is_array() && !state->empty())))
    throw Error(ErrorCode::invalid_argument, source + ": 'state' must be a key or a list of keys (concatenated in order)");
  if (state->is_string()) {
    l.state.push_back(checked_string(*state, source + ": state"));
  } else {
    for (std::size_t i = 0; i < state->size(); ++i)
      l.state.push_back(checked_string((*state)[i], source + ": state[" + std::to_string(i) + "]"));
  }
  if (const auto p = j.find("prompt"); p != j.end()) l.prompt = checked_string(*p, source + ": prompt");
  if (const auto d = j.find("default_prompt"); d != j.end()) {
    if (!d->is_string()) throw Error(ErrorCode::invalid_argument, source + ": default_prompt: expected a string");
    l.default_prompt = d->get<std::string>();
  }
  if (const auto ig = j.find("ignore"); ig != j.end()) {
    if (!ig->is_array()) throw Error(ErrorCode::invalid_argument, source + ": 'ignore' must be a list of keys");
    for (std::size_t i = 0; i < ig->size(); ++i)
      l.ignored.push_back(checked_string((*ig)[i], source + ": ignore[" + std::to_string(i) + "]"));
  }
  // One key, one role: a key listed twice would be read twice or read as two things.
  std::vector<std::string> keys = known_keys(l);
  keys.push_back(std::string(kEpisodeKey));
  keys.push_back(std::string(kSeedKey));
  std::sort(keys.begin(), keys.end());
  if (const auto dup = std::adjacent_find(keys.begin(), keys.end()); dup != keys.end())
    throw Error(ErrorCode::invalid_argument, source + ": key '" + *dup + "' is given more than one role");
  return l;
}

Layouts load_layouts(const std::string& flag_value) {
  Layouts out;
  out.name = flag_value;
  if (flag_value == "auto") {
    out.candidates = builtin_layouts();
    return out;
  }
  for (auto& l : builtin_layouts())
    if (l.name == flag_value) {
      out.candidates.push_back(std::move(l));
      return out;
    }
  std::ifstream in(flag_value, std::ios::binary);
  if (!in)
    throw Error(ErrorCode::invalid_argument, "--openpi-layout '" + flag_value +
                                                 "': neither auto, libero, droid, aloha nor a readable mapping file");
  std::ostringstream text;
  text << in.rdbuf();
  out.candidates.push_back(parse_layout_json(text.str(), flag_value));
  return out;
}

std::vector<std::optional<std::string>> resolve_cameras(const Layout& layout, const models::ModelSpec& spec) {
  std::vector<std::optional<std::string>> out(layout.images.size());
  std::vector<std::string> free = client_cameras(spec);
  auto claim = [&](const std::string& camera) {
    const auto it = std::find(free.begin(), free.end(), camera);
    if (it == free.end()) return false;
    free.erase(it);
    return true;
  };
  for (std::size_t i = 0; i < layout.images.size(); ++i) {
    const auto camera = resolve_camera(layout.images[i].camera, spec);
    if (camera && claim(*camera)) {
      out[i] = *camera;
    } else if (!layout.fill_by_position) {
      fail("unknown_camera", layout.name + ": key '" + layout.images[i].key + "' names camera '" +
                                 layout.images[i].camera + "', which the model does not have or another key feeds" +
                                 " (its cameras: " + join(client_cameras(spec)) + ")");
    }
  }
  if (layout.fill_by_position)
    for (auto& slot : out)
      if (!slot && !free.empty()) {
        slot = free.front();
        free.erase(free.begin());
      }
  return out;
}

ActRequest decode_request(std::string_view frame, const Layouts& layouts, const models::ModelSpec& spec) {
  msgpack::Value root;
  try {
    root = msgpack::parse(frame, kFrameLimits);
  } catch (const msgpack::Error& e) {
    fail("invalid_msgpack", e.what());
  }
  if (!root.is_map())
    fail("invalid_field", std::string("the frame must be a msgpack map of observation keys, got ") +
                              msgpack::kind_name(root.kind));
  std::vector<Leaf> leaves;
  flatten(root, "", leaves);
  const Layout& layout = choose_layout(layouts, leaves);
  for (const auto& leaf : leaves)
    if (!reads_key(layout, leaf.key))
      fail("unknown_field", "unknown key '" + leaf.key + "' for the " + layout.name + " layout (--openpi-layout " +
                                layouts.name + "; it reads: " + join(known_keys(layout)) + ")");

  ActRequest req;
  policy::Observation& obs = req.observation;
  const auto cameras = resolve_cameras(layout, spec);
  for (std::size_t i = 0; i < layout.images.size(); ++i) {
    const msgpack::Value* v = find_leaf(leaves, layout.images[i].key);
    if (!v) continue;
    vision::Image img = decode_image(*v, layout.images[i].key);  // checked even when the model has no camera for it
    if (cameras[i]) obs.images[*cameras[i]] = std::move(img);
  }
  for (const auto& key : layout.state) {
    const msgpack::Value* v = find_leaf(leaves, key);
    if (!v)
      fail("missing_field", "'" + key + "' is required (the state: " + join(layout.state) + ", " +
                                std::to_string(spec.state_dim) + " values in all)");
    append_state(*v, key, obs.state);
  }
  if (const msgpack::Value* p = find_leaf(leaves, layout.prompt)) {
    obs.instruction = decode_text(*p, layout.prompt);
  } else if (layout.default_prompt) {
    obs.instruction = *layout.default_prompt;
  } else {
    fail("missing_field", "'" + layout.prompt + "' is required (the task instruction)");
  }
  if (const msgpack::Value* e = find_leaf(leaves, std::string(kEpisodeKey))) {
    if (!e->is_text_or_bin() || e->bytes.empty())
      fail("invalid_field", std::string(kEpisodeKey) + ": expected a non-empty string");
    req.episode_id = std::string(e->bytes);
  }
  if (const msgpack::Value* s = find_leaf(leaves, std::string(kSeedKey))) {
    if (s->kind != msgpack::Kind::integer || (!s->above_int64 && s->integer < 0))
      fail("invalid_field", std::string(kSeedKey) + ": expected a non-negative integer");
    req.seed = s->above_int64 ? s->uinteger : uint64_t(s->integer);
  }
  check_observation(obs, spec);
  return req;
}

// --- replies ---------------------------------------------------------------------------------------------------

namespace {

void write_json(msgpack::Writer& w, const Json& v) {
  switch (v.type()) {
    case Json::value_t::null: w.nil(); break;
    case Json::value_t::boolean: w.boolean(v.get<bool>()); break;
    case Json::value_t::number_integer: w.integer(v.get<int64_t>()); break;
    case Json::value_t::number_unsigned: w.uinteger(v.get<uint64_t>()); break;
    case Json::value_t::number_float: w.float64(v.get<double>()); break;
    case Json::value_t::string: w.str(v.get_ref<const std::string&>()); break;
    case Json::value_t::array:
      w.array(uint32_t(v.size()));
      for (const auto& item : v) write_json(w, item);
      break;
    case Json::value_t::object:
      w.map(uint32_t(v.size()));
      for (auto it = v.begin(); it != v.end(); ++it) {
        w.str(it.key());
        write_json(w, it.value());
      }
      break;
    default: w.nil(); break;  // binary and discarded values do not occur in answers
  }
}

void write_float32_array(msgpack::Writer& w, const std::vector<float>& values, const std::vector<int64_t>& shape) {
  // msgpack-numpy's own key order and key type (binary), so its unpackb's b"__ndarray__" lookup finds it.
  w.map(4);
  w.bin(std::string_view("__ndarray__"));
  w.boolean(true);
  w.bin(std::string_view("data"));
  w.bin(values.data(), values.size() * sizeof(float));
  w.bin(std::string_view("dtype"));
  w.str("<f4");
  w.bin(std::string_view("shape"));
  w.array(uint32_t(shape.size()));
  for (int64_t d : shape) w.integer(d);
}

}  // namespace

std::string encode_json(const Json& value) {
  msgpack::Writer w;
  write_json(w, value);
  return w.take();
}

std::string encode_float32_array(const std::vector<float>& values, const std::vector<int64_t>& shape) {
  msgpack::Writer w;
  write_float32_array(w, values, shape);
  return w.take();
}

std::string encode_reply(const Json& act_body, const ServerTiming& timing) {
  const Json& rows = act_body.at("actions");
  const int64_t dim = act_body.value("action_dim", rows.empty() ? int64_t(0) : int64_t(rows.front().size()));
  std::vector<float> values;
  values.reserve(rows.size() * std::size_t(dim));
  for (const auto& row : rows) {
    if (int64_t(row.size()) != dim) throw Error(ErrorCode::internal, "openpi: ragged actions in an /act answer");
    for (const auto& x : row) values.push_back(x.is_number() ? x.get<float>() : std::numeric_limits<float>::quiet_NaN());
  }
  // The forward pass, as openpi's policy_timing times its model; absent (0) when no forward pass ran (a skip, a
  // fallback, a deadline answer).
  double policy_ms = 0;
  if (const auto latency = act_body.find("latency_ms"); latency != act_body.end() && latency->is_object())
    if (const auto p = latency->find("predict"); p != latency->end() && p->is_number()) policy_ms = p->get<double>();
  Json rest = Json::object();
  for (auto it = act_body.begin(); it != act_body.end(); ++it)
    if (it.key() != "actions") rest[it.key()] = it.value();

  msgpack::Writer w;
  w.map(4);
  w.str("actions");
  write_float32_array(w, values, {int64_t(rows.size()), dim});
  w.str("policy_timing");
  write_json(w, Json{{"infer_ms", policy_ms}});
  w.str("server_timing");
  Json server = {{"infer_ms", timing.infer_ms}};
  if (timing.prev_total_ms) server["prev_total_ms"] = *timing.prev_total_ms;
  write_json(w, server);
  w.str("tether");
  write_json(w, rest);
  return w.take();
}

}  // namespace tether::serve::openpi
