// POST /act body parsing: strict schema, stable error codes, images decoded here so a bad one fails only its request.
#include "serve/act_request.h"

#include <cmath>

#include "serve/base64.h"
#include "vision/image.h"

namespace tether::serve {

namespace {

using J = nlohmann::json;  // request key order carries no meaning

[[noreturn]] void fail(const std::string& code, const std::string& message) { throw HttpError(400, code, message); }

std::string type_name(const J& v) { return v.type_name(); }

void check_pixels(int64_t height, int64_t width, const std::string& where) {
  if (height < 1 || width < 1) fail("invalid_field", where + ": an image needs at least one pixel");
  if (height > vision::kMaxImagePixels / width)
    fail("invalid_field", where + ": " + std::to_string(height) + "x" + std::to_string(width) + " exceeds the " +
                              std::to_string(vision::kMaxImagePixels) + "-pixel limit");
}

void check_state(const std::vector<float>& state, const models::ModelSpec& spec) {
  if (int64_t(state.size()) != spec.state_dim)
    fail("invalid_state", "state has " + std::to_string(state.size()) + " values, the model expects " + std::to_string(spec.state_dim));
  for (std::size_t i = 0; i < state.size(); ++i)
    if (!std::isfinite(state[i])) fail("invalid_state", "state[" + std::to_string(i) + "] is not a finite float32");
}

vision::Image decode_raw(const J& obj, const std::string& field) {
  for (auto it = obj.begin(); it != obj.end(); ++it)
    if (it.key() != "data" && it.key() != "shape")
      fail("invalid_field", field + ": unexpected key '" + it.key() + "' (a raw image has only 'data' and 'shape')");
  const auto data = obj.find("data");
  const auto shape = obj.find("shape");
  if (data == obj.end() || shape == obj.end())
    fail("invalid_field", field + ": a raw image needs both 'data' (base64 of uint8 RGB) and 'shape' ([H, W, 3])");
  if (!data->is_string()) fail("invalid_field", field + ".data: expected a base64 string, got " + type_name(*data));
  if (!shape->is_array() || shape->size() != 3)
    fail("invalid_field", field + ".shape: expected [H, W, 3]");
  int64_t dims[3];
  for (int i = 0; i < 3; ++i) {
    const J& d = (*shape)[std::size_t(i)];
    if (!d.is_number_integer() || d.get<int64_t>() < 1 || d.get<int64_t>() > 1'000'000)
      fail("invalid_field", field + ".shape[" + std::to_string(i) + "]: expected a positive integer");
    dims[i] = d.get<int64_t>();
  }
  if (dims[2] != 3) fail("invalid_field", field + ".shape: the last dimension must be 3 (RGB), got " + std::to_string(dims[2]));
  check_pixels(dims[0], dims[1], field + ".shape");
  std::string why;
  auto bytes = base64_decode(data->get_ref<const std::string&>(), &why);
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

vision::Image decode_field_image(const J& v, const std::string& field) {
  if (v.is_object()) return decode_raw(v, field);
  if (!v.is_string())
    fail("invalid_field", field + ": expected a base64 PNG/JPEG string or {\"data\", \"shape\"}, got " + type_name(v));
  const auto& text = v.get_ref<const std::string&>();
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

RtcFields parse_rtc(const J& rtc, const models::ModelSpec& spec) {
  if (!rtc.is_object()) fail("invalid_field", "rtc: expected an object {prev_actions, inference_delay}, got " + type_name(rtc));
  for (auto it = rtc.begin(); it != rtc.end(); ++it)
    if (it.key() != "prev_actions" && it.key() != "inference_delay")
      fail("unknown_field", "rtc: unknown field '" + it.key() + "' (accepted: prev_actions, inference_delay)");
  RtcFields out;
  const auto prev = rtc.find("prev_actions");
  if (prev == rtc.end() || !prev->is_array() || prev->empty() || int64_t(prev->size()) > spec.chunk_size)
    fail("invalid_field", "rtc.prev_actions: expected 1 to " + std::to_string(spec.chunk_size) + " rows of " +
                              std::to_string(spec.action_dim) + " numbers (the previous chunk's actions not yet executed)");
  out.rows = int64_t(prev->size());
  out.prev_actions.reserve(std::size_t(out.rows * spec.action_dim));
  for (std::size_t r = 0; r < prev->size(); ++r) {
    const J& row = (*prev)[r];
    const std::string where = "rtc.prev_actions[" + std::to_string(r) + "]";
    if (!row.is_array() || int64_t(row.size()) != spec.action_dim)
      fail("invalid_field", where + ": expected " + std::to_string(spec.action_dim) + " numbers");
    for (std::size_t c = 0; c < row.size(); ++c) {
      const float v = row[c].is_number() ? float(row[c].get<double>()) : NAN;
      if (!std::isfinite(v)) fail("invalid_field", where + "[" + std::to_string(c) + "]: expected a finite number");
      out.prev_actions.push_back(v);
    }
  }
  const auto delay = rtc.find("inference_delay");
  if (delay != rtc.end() && !delay->is_null()) {
    if (!delay->is_number_integer() || delay->get<int64_t>() < 0 || delay->get<int64_t>() >= spec.chunk_size)
      fail("invalid_field", "rtc.inference_delay: expected an integer in [0, " + std::to_string(spec.chunk_size) + ")");
    out.inference_delay = int(delay->get<int64_t>());
  }
  return out;
}

}  // namespace

ActRequest parse_act_request(std::string_view body, const models::ModelSpec& spec) {
  const J j = parse_json(body);
  if (!j.is_object()) fail("bad_json", "the body must be a JSON object, got " + type_name(j));

  static const char* const kKnown[] = {"instruction", "state", "images", "image", "episode_id", "seed", "rtc"};
  for (auto it = j.begin(); it != j.end(); ++it) {
    bool known = false;
    for (const char* k : kKnown) known = known || it.key() == k;
    if (!known)
      fail("unknown_field", "unknown field '" + it.key() + "' (accepted: instruction, state, images, image, episode_id, seed, rtc)");
  }

  ActRequest req;
  policy::Observation& obs = req.observation;

  const auto instruction = j.find("instruction");
  if (instruction == j.end() || instruction->is_null()) fail("missing_field", "'instruction' is required");
  if (!instruction->is_string()) fail("invalid_field", "instruction: expected a string, got " + type_name(*instruction));
  obs.instruction = instruction->get<std::string>();

  const auto state = j.find("state");
  if (state == j.end() || state->is_null()) fail("missing_field", "'state' is required (" + std::to_string(spec.state_dim) + " numbers)");
  if (!state->is_array()) fail("invalid_field", "state: expected an array of numbers, got " + type_name(*state));
  for (std::size_t i = 0; i < state->size(); ++i)
    if (!(*state)[i].is_number()) fail("invalid_field", "state[" + std::to_string(i) + "]: expected a number, got " + type_name((*state)[i]));
  if (int64_t(state->size()) != spec.state_dim)
    fail("invalid_state", "state has " + std::to_string(state->size()) + " values, the model expects " + std::to_string(spec.state_dim));
  obs.state.reserve(state->size());
  for (std::size_t i = 0; i < state->size(); ++i) obs.state.push_back(float((*state)[i].get<double>()));
  check_state(obs.state, spec);

  const auto images = j.find("images");
  const auto image = j.find("image");
  const bool has_images = images != j.end() && !images->is_null();
  const bool has_image = image != j.end() && !image->is_null();
  if (has_images && has_image) fail("invalid_field", "give either 'image' (the first camera) or 'images', not both");
  if (!has_images && !has_image) fail("missing_field", "an image is required: 'images' {camera: image} or 'image'");
  if (has_image) {
    if (spec.cameras.empty()) fail("unknown_camera", "the model has no camera inputs");
    obs.images[spec.cameras.front()] = decode_field_image(*image, "image");
  } else {
    if (!images->is_object()) fail("invalid_field", "images: expected an object {camera: image}, got " + type_name(*images));
    if (images->empty()) fail("missing_field", "images: at least one camera image is required");
    for (auto it = images->begin(); it != images->end(); ++it) {
      const auto camera = resolve_camera(it.key(), spec);
      if (!camera) {
        std::string known;
        for (const auto& c : spec.cameras) known += (known.empty() ? "" : ", ") + c;
        fail("unknown_camera", "images: the model has no camera '" + it.key() + "' (it has: " + known + ")");
      }
      if (obs.images.count(*camera)) fail("invalid_field", "images: camera '" + *camera + "' is given twice");
      obs.images[*camera] = decode_field_image(it.value(), "images." + it.key());
    }
  }

  const auto episode = j.find("episode_id");
  if (episode != j.end() && !episode->is_null()) {
    if (!episode->is_string()) fail("invalid_field", "episode_id: expected a string, got " + type_name(*episode));
    req.episode_id = episode->get<std::string>();
  }
  const auto rtc = j.find("rtc");
  if (rtc != j.end() && !rtc->is_null()) req.rtc = parse_rtc(*rtc, spec);
  const auto seed = j.find("seed");
  if (seed != j.end() && !seed->is_null()) {
    if (!seed->is_number_integer() || (seed->is_number_integer() && !seed->is_number_unsigned() && seed->get<int64_t>() < 0))
      fail("invalid_field", "seed: expected an integer >= 0");
    req.seed = seed->get<uint64_t>();
  }
  return req;
}

void check_observation(const policy::Observation& obs, const models::ModelSpec& spec) {
  check_state(obs.state, spec);
  if (obs.images.empty()) fail("missing_field", "an image is required: the request names no camera the model has");
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
