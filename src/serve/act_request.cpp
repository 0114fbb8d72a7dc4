// POST /act body parsing: strict schema, stable error codes, images decoded here so a bad one fails only its request.
#include "serve/act_request.h"

#include <simdjson.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <memory>
#include <vector>

#include "serve/base64.h"
#include "vision/image.h"

namespace tether::serve {

namespace {

using J = nlohmann::json;  // request key order carries no meaning

[[noreturn]] void fail(const std::string& code, const std::string& message) { throw HttpError(400, code, message); }

void check_pixels(int64_t height, int64_t width, const std::string& where) {
  if (height < 1 || width < 1) fail("invalid_field", where + ": an image needs at least one pixel");
  if (height > vision::kMaxImagePixels / width)
    fail("invalid_field", where + ": " + std::to_string(height) + "x" + std::to_string(width) + " exceeds the " +
                              std::to_string(vision::kMaxImagePixels) + "-pixel limit");
}

// A model that needs every camera (models::ModelSpec::every_camera_required) refuses a request without one.
void check_cameras(const policy::Observation& obs, const models::ModelSpec& spec) {
  if (!spec.every_camera_required) return;
  for (const auto& c : spec.cameras)
    if (!obs.images.count(c) &&
        std::find(spec.synthetic_cameras.begin(), spec.synthetic_cameras.end(), c) == spec.synthetic_cameras.end())
      fail("missing_field", "no image for camera '" + c + "': " + spec.missing_camera_rule);
}

void check_state(const std::vector<float>& state, const models::ModelSpec& spec) {
  if (int64_t(state.size()) != spec.state_dim)
    fail("invalid_state", "state has " + std::to_string(state.size()) + " values, the model expects " + std::to_string(spec.state_dim));
  for (std::size_t i = 0; i < state.size(); ++i)
    if (!std::isfinite(state[i])) fail("invalid_state", "state[" + std::to_string(i) + "] is not a finite float32");
}

// The body is read with simdjson's DOM parser: it validates the whole document before any field is looked at, as
// nlohmann did, so a request gets the same error whatever the order of its mistakes (the on-demand API validates only
// what it reaches). A document simdjson refuses, or one with a repeated key, is read by nlohmann (parse_json below),
// whose verdict and messages are the contract's, and handed back to simdjson as nlohmann writes it.
using E = simdjson::dom::element;
using Fields = std::vector<std::pair<std::string_view, E>>;

// Thrown where nlohmann's reading must decide (a repeated key: nlohmann keeps the last value).
struct ReadWithNlohmann {};

std::string type_name(E v) {
  switch (v.type()) {
    case simdjson::dom::element_type::ARRAY: return "array";
    case simdjson::dom::element_type::OBJECT: return "object";
    case simdjson::dom::element_type::STRING: return "string";
    case simdjson::dom::element_type::BOOL: return "boolean";
    case simdjson::dom::element_type::NULL_VALUE: return "null";
    default: return "number";
  }
}

// An object's fields in key order, as nlohmann::json (a std::map) lists them, so the first of several faults is the
// same one as before.
Fields sorted_fields(simdjson::dom::object obj) {
  Fields fields;
  for (auto field : obj) fields.emplace_back(field.key, field.value);
  std::sort(fields.begin(), fields.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
  for (std::size_t i = 1; i < fields.size(); ++i)
    if (fields[i - 1].first == fields[i].first) throw ReadWithNlohmann{};
  return fields;
}

// The field `key`, or nullopt when it is absent or null.
std::optional<E> present(const Fields& fields, std::string_view key) {
  for (const auto& [k, v] : fields)
    if (k == key) return v.is_null() ? std::nullopt : std::optional<E>(v);
  return std::nullopt;
}

bool is_integer(E v) { return v.is_int64() || v.is_uint64(); }

// An integer's value, with values above INT64_MAX saturated (every range checked here is far below it).
int64_t integer_value(E v) {
  if (v.is_int64()) return int64_t(v.get_int64());
  return int64_t(std::min<uint64_t>(v.get_uint64(), uint64_t(INT64_MAX)));
}

std::string_view string_value(E v) { return std::string_view(v.get_string()); }

vision::Image decode_raw(simdjson::dom::object obj, const std::string& field) {
  const Fields fields = sorted_fields(obj);
  for (const auto& [key, value] : fields)
    if (key != "data" && key != "shape")
      fail("invalid_field", field + ": unexpected key '" + std::string(key) + "' (a raw image has only 'data' and 'shape')");
  std::optional<E> data, shape;
  for (const auto& [key, value] : fields) (key == "data" ? data : shape) = value;
  if (!data || !shape)
    fail("invalid_field", field + ": a raw image needs both 'data' (base64 of uint8 RGB) and 'shape' ([H, W, 3])");
  if (!data->is_string()) fail("invalid_field", field + ".data: expected a base64 string, got " + type_name(*data));
  if (!shape->is_array() || simdjson::dom::array(*shape).size() != 3)
    fail("invalid_field", field + ".shape: expected [H, W, 3]");
  int64_t dims[3];
  int i = 0;
  for (E d : simdjson::dom::array(*shape)) {
    if (!is_integer(d) || integer_value(d) < 1 || integer_value(d) > 1'000'000)
      fail("invalid_field", field + ".shape[" + std::to_string(i) + "]: expected a positive integer");
    dims[i++] = integer_value(d);
  }
  if (dims[2] != 3) fail("invalid_field", field + ".shape: the last dimension must be 3 (RGB), got " + std::to_string(dims[2]));
  check_pixels(dims[0], dims[1], field + ".shape");
  std::string why;
  auto bytes = base64_decode(string_value(*data), &why);
  if (!bytes) fail("invalid_field", field + ".data: " + why);
  const auto expected = std::size_t(dims[0] * dims[1] * 3);
  if (bytes->size() != expected)
    fail("invalid_field", field + ".data: " + std::to_string(bytes->size()) + " bytes, shape [" + std::to_string(dims[0]) +
                              ", " + std::to_string(dims[1]) + ", 3] needs " + std::to_string(expected));
  vision::Image img;
  img.height = int(dims[0]);
  img.width = int(dims[1]);
  img.rgb = std::move(*bytes);
  return img;
}

vision::Image decode_field_image(E v, const std::string& field) {
  if (v.is_object()) return decode_raw(v, field);
  if (!v.is_string())
    fail("invalid_field", field + ": expected a base64 PNG/JPEG string or {\"data\", \"shape\"}, got " + type_name(v));
  const std::string_view text = string_value(v);
  if (text.empty()) fail("invalid_field", field + ": empty image");
  std::string why;
  auto bytes = base64_decode(text, &why);
  if (!bytes) fail("invalid_field", field + ": " + why);
  try {
    return vision::decode_image(bytes->data(), bytes->size(), field);
  } catch (const std::exception& e) {
    fail("invalid_image", e.what());
  }
}

}  // namespace

std::optional<std::string> resolve_camera(const std::string& name, const models::ModelSpec& spec) {
  return models::find_camera(spec, name);
}

namespace {

// Replaces each occurrence of the number `literal` outside strings by `replacement`; false if none was found.
bool replace_number_token(std::string& text, const std::string& literal, const std::string& replacement) {
  bool in_string = false, replaced = false;
  for (std::size_t i = 0; i < text.size(); ++i) {
    const char c = text[i];
    if (in_string) {
      if (c == '\\') ++i;
      else if (c == '"') in_string = false;
      continue;
    }
    if (c == '"') {
      in_string = true;
      continue;
    }
    const bool starts_token = i == 0 || std::string_view(",:[ \t\r\n").find(text[i - 1]) != std::string_view::npos;
    const std::size_t end = i + literal.size();
    const bool ends_token = end >= text.size() || std::string_view(",]} \t\r\n").find(text[end]) != std::string_view::npos;
    if (starts_token && ends_token && text.compare(i, literal.size(), literal) == 0) {
      text.replace(i, literal.size(), replacement);
      i += replacement.size() - 1;
      replaced = true;
    }
  }
  return replaced;
}

J parse_json(std::string_view body) {
  // The callback caps nesting before any deep structure is built.
  auto depth_guard = [](int depth, J::parse_event_t, J&) {
    if (depth > kMaxJsonDepth)
      throw HttpError(400, "bad_json", "JSON nested deeper than " + std::to_string(kMaxJsonDepth) + " levels");
    return true;
  };
  std::string patched;  // only used when a number overflows a double
  for (int attempt = 0;; ++attempt) {
    try {
      return patched.empty() ? J::parse(body.begin(), body.end(), depth_guard) : J::parse(patched, depth_guard);
    } catch (const HttpError&) {
      throw;
    } catch (const J::out_of_range& e) {
      // Valid JSON whose number is beyond double range (1e999): the value, not the syntax, is wrong, so it is
      // parsed as the largest double of its sign and judged by the field's own check (state: not a finite float32).
      const std::string what = e.what();
      const auto open = what.find('\''), close = what.rfind('\'');
      if (e.id != 406 || attempt >= 8 || open == std::string::npos || close <= open + 1)
        fail("bad_json", std::string("the body is not valid JSON: ") + e.what());
      const std::string literal = what.substr(open + 1, close - open - 1);
      if (patched.empty()) patched.assign(body);
      if (!replace_number_token(patched, literal, literal[0] == '-' ? "-1.7976931348623157e308" : "1.7976931348623157e308"))
        fail("bad_json", std::string("the body is not valid JSON: ") + e.what());
    } catch (const J::exception& e) {
      fail("bad_json", std::string("the body is not valid JSON: ") + e.what());
    }
  }
}

RtcFields parse_rtc(E rtc, const models::ModelSpec& spec) {
  if (!rtc.is_object()) fail("invalid_field", "rtc: expected an object {prev_actions, inference_delay}, got " + type_name(rtc));
  const Fields fields = sorted_fields(rtc);
  for (const auto& [key, value] : fields)
    if (key != "prev_actions" && key != "inference_delay")
      fail("unknown_field", "rtc: unknown field '" + std::string(key) + "' (accepted: prev_actions, inference_delay)");
  RtcFields out;
  std::optional<E> prev;
  for (const auto& [key, value] : fields)
    if (key == "prev_actions") prev = value;
  if (!prev || !prev->is_array() || simdjson::dom::array(*prev).size() == 0 ||
      int64_t(simdjson::dom::array(*prev).size()) > spec.chunk_size)
    fail("invalid_field", "rtc.prev_actions: expected 1 to " + std::to_string(spec.chunk_size) + " rows of " +
                              std::to_string(spec.action_dim) + " numbers (the previous chunk's actions not yet executed)");
  out.rows = int64_t(simdjson::dom::array(*prev).size());
  out.prev_actions.reserve(std::size_t(out.rows * spec.action_dim));
  std::size_t r = 0;
  for (E row : simdjson::dom::array(*prev)) {
    const std::string where = "rtc.prev_actions[" + std::to_string(r++) + "]";
    if (!row.is_array() || int64_t(simdjson::dom::array(row).size()) != spec.action_dim)
      fail("invalid_field", where + ": expected " + std::to_string(spec.action_dim) + " numbers");
    std::size_t c = 0;
    for (E value : simdjson::dom::array(row)) {
      const float v = value.is_number() ? float(double(value.get_double())) : NAN;
      if (!std::isfinite(v)) fail("invalid_field", where + "[" + std::to_string(c) + "]: expected a finite number");
      out.prev_actions.push_back(v);
      ++c;
    }
  }
  if (const auto delay = present(fields, "inference_delay")) {
    if (!is_integer(*delay) || integer_value(*delay) < 0 || integer_value(*delay) >= spec.chunk_size)
      fail("invalid_field", "rtc.inference_delay: expected an integer in [0, " + std::to_string(spec.chunk_size) + ")");
    out.inference_delay = int(integer_value(*delay));
  }
  return out;
}

ActRequest read_act_request(E root, const models::ModelSpec& spec) {
  if (!root.is_object()) fail("bad_json", "the body must be a JSON object, got " + type_name(root));
  const Fields fields = sorted_fields(root);

  static const char* const kKnown[] = {"instruction", "state",       "images", "image", "episode_id",
                                       "seed",        "rtc", "embodiment_tag"};
  for (const auto& [key, value] : fields) {
    bool known = false;
    for (const char* k : kKnown) known = known || key == k;
    if (!known)
      fail("unknown_field", "unknown field '" + std::string(key) +
                                "' (accepted: instruction, state, images, image, episode_id, seed, rtc, embodiment_tag)");
  }

  ActRequest req;
  policy::Observation& obs = req.observation;

  const auto instruction = present(fields, "instruction");
  if (!instruction) fail("missing_field", "'instruction' is required");
  if (!instruction->is_string()) fail("invalid_field", "instruction: expected a string, got " + type_name(*instruction));
  obs.instruction = std::string(string_value(*instruction));

  const auto state = present(fields, "state");
  if (!state) fail("missing_field", "'state' is required (" + std::to_string(spec.state_dim) + " numbers)");
  if (!state->is_array()) fail("invalid_field", "state: expected an array of numbers, got " + type_name(*state));
  const simdjson::dom::array values = *state;
  std::size_t i = 0;
  for (E v : values) {
    if (!v.is_number()) fail("invalid_field", "state[" + std::to_string(i) + "]: expected a number, got " + type_name(v));
    ++i;
  }
  if (int64_t(values.size()) != spec.state_dim)
    fail("invalid_state", "state has " + std::to_string(values.size()) + " values, the model expects " + std::to_string(spec.state_dim));
  obs.state.reserve(values.size());
  for (E v : values) obs.state.push_back(float(double(v.get_double())));
  check_state(obs.state, spec);

  const auto images = present(fields, "images");
  const auto image = present(fields, "image");
  if (images && image) fail("invalid_field", "give either 'image' (the first camera) or 'images', not both");
  if (!images && !image) fail("missing_field", "an image is required: 'images' {camera: image} or 'image'");
  if (image) {
    if (spec.cameras.empty()) fail("unknown_camera", "the model has no camera inputs");
    obs.images[spec.cameras.front()] = decode_field_image(*image, "image");
  } else {
    if (!images->is_object()) fail("invalid_field", "images: expected an object {camera: image}, got " + type_name(*images));
    const Fields cameras = sorted_fields(*images);
    if (cameras.empty()) fail("missing_field", "images: at least one camera image is required");
    for (const auto& [key, value] : cameras) {
      const std::string name(key);
      const auto camera = resolve_camera(name, spec);
      if (!camera) {
        std::string known;
        for (const auto& c : spec.cameras) known += (known.empty() ? "" : ", ") + c;
        fail("unknown_camera", "images: the model has no camera '" + name + "' (it has: " + known + ")");
      }
      if (obs.images.count(*camera)) fail("invalid_field", "images: camera '" + *camera + "' is given twice");
      obs.images[*camera] = decode_field_image(value, "images." + name);
    }
  }

  check_cameras(obs, spec);

  if (const auto tag = present(fields, "embodiment_tag")) {
    if (!tag->is_string()) fail("invalid_field", "embodiment_tag: expected a string, got " + type_name(*tag));
    // The pipeline routed the request by this tag (act_request_embodiment) to the host whose spec this is.
    if (string_value(*tag) != spec.embodiment)
      fail("invalid_field", "embodiment_tag: '" + std::string(string_value(*tag)) + "' is not the embodiment '" +
                                spec.embodiment + "' this request was decoded for");
    req.embodiment = spec.embodiment;
  }
  if (const auto episode = present(fields, "episode_id")) {
    if (!episode->is_string()) fail("invalid_field", "episode_id: expected a string, got " + type_name(*episode));
    req.episode_id = std::string(string_value(*episode));
  }
  if (const auto rtc = present(fields, "rtc")) req.rtc = parse_rtc(*rtc, spec);
  if (const auto seed = present(fields, "seed")) {
    if (!is_integer(*seed) || (seed->is_int64() && int64_t(seed->get_int64()) < 0))
      fail("invalid_field", "seed: expected an integer >= 0");
    req.seed = seed->is_int64() ? uint64_t(int64_t(seed->get_int64())) : uint64_t(seed->get_uint64());
  }
  return req;
}

// One parser per I/O thread, reused: its buffers grow to the largest body seen, so a huge one is let go afterwards.
constexpr std::size_t kKeptParserCapacity = std::size_t(4) << 20;

// Deeper than nlohmann's limit is left to nlohmann, which refuses it with its message.
constexpr std::size_t kSimdjsonMaxDepth = kMaxJsonDepth + 2;

}  // namespace

namespace {

// The I/O thread's parser (one per thread, reused), let go when a huge body grew it past kKeptParserCapacity.
struct ThreadParser {
  ThreadParser() : p(slot()) {
    if (!p) {
      p = std::make_unique<simdjson::dom::parser>();
      if (p->allocate(simdjson::dom::MINIMAL_DOCUMENT_CAPACITY, kSimdjsonMaxDepth) != simdjson::SUCCESS)
        throw std::bad_alloc();
    }
  }
  ~ThreadParser() {
    if (p && p->capacity() > kKeptParserCapacity) p.reset();
  }
  simdjson::dom::parser* operator->() { return p.get(); }
  static std::unique_ptr<simdjson::dom::parser>& slot() {
    thread_local std::unique_ptr<simdjson::dom::parser> parser;
    return parser;
  }
  std::unique_ptr<simdjson::dom::parser>& p;
};

}  // namespace

std::string act_request_embodiment(std::string_view body) {
  ThreadParser parser;
  E root;
  if (parser->parse(body.data(), body.size()).get(root) != simdjson::SUCCESS || !root.is_object()) return "";
  E tag;
  if (root.at_key("embodiment_tag").get(tag) != simdjson::SUCCESS || !tag.is_string()) return "";
  return std::string(string_value(tag));
}

ActRequest parse_act_request(std::string_view body, const models::ModelSpec& spec) {
  ThreadParser parser;
  E root;
  if (parser->parse(body.data(), body.size()).get(root) == simdjson::SUCCESS) {
    try {
      return read_act_request(root, spec);
    } catch (const ReadWithNlohmann&) {
    }
  }
  // Refused by simdjson (malformed, a number beyond double range, too deep) or a repeated key: nlohmann's reading is
  // the contract (its error, or the document as it understands it, written back without repeats).
  const std::string normalised = parse_json(body).dump();
  const auto again = parser->parse(normalised);
  if (again.error() != simdjson::SUCCESS)
    fail("bad_json", std::string("the body is not valid JSON: ") + simdjson::error_message(again.error()));
  return read_act_request(again.value_unsafe(), spec);
}

void check_observation(const policy::Observation& obs, const models::ModelSpec& spec) {
  check_state(obs.state, spec);
  if (obs.images.empty()) fail("missing_field", "an image is required: the request names no camera the model has");
  check_cameras(obs, spec);
}

vision::Image raw_rgb_image(const uint8_t* data, int64_t height, int64_t width, const std::string& field) {
  check_pixels(height, width, field);
  vision::Image img;
  img.height = int(height);
  img.width = int(width);
  img.rgb.assign(data, data + height * width * 3);
  return img;
}

std::string act_request_json(const ActRequest& req) {
  const policy::Observation& obs = req.observation;
  J images = J::object();
  for (const auto& [camera, img] : obs.images)
    images[camera] = {{"data", base64_encode(img.rgb.data(), img.rgb.size())}, {"shape", {img.height, img.width, 3}}};
  J body = {{"instruction", obs.instruction}, {"state", obs.state}, {"images", std::move(images)}};
  if (req.seed) body["seed"] = *req.seed;
  if (req.episode_id) body["episode_id"] = *req.episode_id;
  if (!req.embodiment.empty()) body["embodiment_tag"] = req.embodiment;
  if (req.rtc) {
    const int64_t dim = req.rtc->rows > 0 ? int64_t(req.rtc->prev_actions.size()) / req.rtc->rows : 0;
    J rows = J::array();
    for (int64_t r = 0; r < req.rtc->rows; ++r)
      rows.push_back(std::vector<float>(req.rtc->prev_actions.begin() + r * dim,
                                        req.rtc->prev_actions.begin() + (r + 1) * dim));
    body["rtc"] = {{"prev_actions", std::move(rows)}, {"inference_delay", req.rtc->inference_delay}};
  }
  return body.dump();
}

}  // namespace tether::serve
