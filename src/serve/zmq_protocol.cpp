// Tether's ZMQ protocol: decoding requests and encoding replies (no sockets here).
#include "serve/zmq_protocol.h"

#include <cmath>
#include <iterator>

#include "serve/http_error.h"
#include "serve/msgpack_json.h"
#include "vision/image.h"

namespace tether::serve::zmqp {

namespace {

[[noreturn]] void fail(const std::string& code, const std::string& message) { throw HttpError(400, code, message); }

std::string kind_of(const msgpack::Value& v) { return msgpack::kind_name(v.kind); }

const char* const kFields =
    "instruction, state, image, images, episode_id, seed, rtc, embodiment_tag, api_key, request_id, id";
const char* const kHttpFields =
    "instruction, state, image, images, episode_id, seed, rtc, embodiment_tag; the key and the request id travel as "
    "headers";

const msgpack::Value* field(const msgpack::Value& map, std::string_view key) {
  const msgpack::Value* v = map.find(key);
  return v && !v->is_nil() ? v : nullptr;
}

int64_t integer_of(const msgpack::Value& v, const std::string& where) {
  if (v.kind != msgpack::Kind::integer || v.above_int64) fail("invalid_field", where + ": expected an integer");
  return v.integer;
}

vision::Image image_of(const msgpack::Value& v, const std::string& where) {
  if (v.is_bin() || v.is_str()) {
    if (v.bytes.empty()) fail("invalid_field", where + ": empty image");
    try {
      return vision::decode_image(reinterpret_cast<const uint8_t*>(v.bytes.data()), v.bytes.size(), where);
    } catch (const HttpError&) {
      throw;
    } catch (const std::exception& e) {
      fail("invalid_image", e.what());
    }
  }
  if (!v.is_map())
    fail("invalid_field", where + ": expected PNG/JPEG bytes or {\"data\": bin, \"shape\": [H, W, 3]}, got " + kind_of(v));
  for (const auto& [k, _] : v.entries)
    if (!k.is_text_or_bin() || (k.bytes != "data" && k.bytes != "shape"))
      fail("invalid_field", where + ": a raw image has only 'data' and 'shape'");
  const msgpack::Value* data = field(v, "data");
  const msgpack::Value* shape = field(v, "shape");
  if (!data || !shape) fail("invalid_field", where + ": a raw image needs both 'data' (uint8 RGB bytes) and 'shape' ([H, W, 3])");
  if (!data->is_bin() && !data->is_str()) fail("invalid_field", where + ".data: expected bytes, got " + kind_of(*data));
  if (!shape->is_array() || shape->items.size() != 3)
    fail("invalid_field", where + ".shape: expected [H, W, 3]");
  const int64_t h = integer_of(shape->items[0], where + ".shape[0]"), w = integer_of(shape->items[1], where + ".shape[1]");
  if (integer_of(shape->items[2], where + ".shape[2]") != 3) fail("invalid_field", where + ".shape: expected 3 channels (RGB)");
  if (h < 1 || w < 1) fail("invalid_field", where + ".shape: height and width must be at least 1");
  if (h > vision::kMaxImagePixels || w > vision::kMaxImagePixels / h) fail("invalid_field", where + ": larger than the " + std::to_string(vision::kMaxImagePixels) + "-pixel limit");
  if (uint64_t(data->bytes.size()) != uint64_t(h) * uint64_t(w) * 3)
    fail("invalid_field", where + ".data: " + std::to_string(data->bytes.size()) + " bytes, the shape needs " +
                              std::to_string(h * w * 3));
  return raw_rgb_image(reinterpret_cast<const uint8_t*>(data->bytes.data()), h, w, where);
}

std::vector<float> numbers(const msgpack::Value& v, const std::string& where) {
  if (!v.is_array()) fail("invalid_field", where + ": expected an array of numbers, got " + kind_of(v));
  std::vector<float> out;
  out.reserve(v.items.size());
  for (std::size_t i = 0; i < v.items.size(); ++i) {
    if (!v.items[i].is_number())
      fail("invalid_field", where + "[" + std::to_string(i) + "]: expected a number, got " + kind_of(v.items[i]));
    out.push_back(float(v.items[i].as_double()));
  }
  return out;
}

RtcFields rtc_of(const msgpack::Value& v, const models::ModelSpec& spec) {
  if (!v.is_map()) fail("invalid_field", "rtc: expected a map {prev_actions, inference_delay}, got " + kind_of(v));
  for (const auto& [k, _] : v.entries)
    if (!k.is_text_or_bin() || (k.bytes != "prev_actions" && k.bytes != "inference_delay"))
      fail("unknown_field", "rtc: unknown field (accepted: prev_actions, inference_delay)");
  const msgpack::Value* prev = field(v, "prev_actions");
  if (!prev || !prev->is_array() || prev->items.empty() || int64_t(prev->items.size()) > spec.chunk_size)
    fail("invalid_field", "rtc.prev_actions: expected 1 to " + std::to_string(spec.chunk_size) + " rows of " +
                              std::to_string(spec.action_dim) + " numbers (the previous chunk's actions not yet executed)");
  RtcFields out;
  out.rows = int64_t(prev->items.size());
  for (std::size_t r = 0; r < prev->items.size(); ++r) {
    const std::string where = "rtc.prev_actions[" + std::to_string(r) + "]";
    const std::vector<float> row = numbers(prev->items[r], where);
    if (int64_t(row.size()) != spec.action_dim)
      fail("invalid_field", where + ": expected " + std::to_string(spec.action_dim) + " numbers");
    for (std::size_t c = 0; c < row.size(); ++c)
      if (!std::isfinite(row[c])) fail("invalid_field", where + "[" + std::to_string(c) + "]: expected a finite number");
    out.prev_actions.insert(out.prev_actions.end(), row.begin(), row.end());
  }
  if (const msgpack::Value* d = field(v, "inference_delay")) {
    if (d->kind != msgpack::Kind::integer || d->above_int64 || d->integer < 0 || d->integer >= spec.chunk_size)
      fail("invalid_field", "rtc.inference_delay: expected an integer in [0, " + std::to_string(spec.chunk_size) + ")");
    out.inference_delay = int(d->integer);
  }
  return out;
}

void write_body(msgpack::Writer& w, const Json& body) {
  for (auto it = body.begin(); it != body.end(); ++it) {
    w.str(it.key());
    if (it.key() == "actions" && it.value().is_array()) {
      w.array(uint32_t(it.value().size()));
      for (const auto& row : it.value()) {
        w.array(uint32_t(row.size()));
        for (const auto& x : row) w.float32(x.get<float>());
      }
    } else {
      msgpack::write_json(w, it.value());
    }
  }
}

}  // namespace

Request parse_request(std::string_view message) {
  Request req;
  req.root = msgpack::parse_map(message, "message", "with /act's fields");
  if (const msgpack::Value* id = field(req.root, "id")) {
    if (id->is_str() && id->bytes.size() <= 128) req.id = std::string(id->bytes);
    else if (id->kind == msgpack::Kind::integer && !id->above_int64) req.id = id->integer;
    else fail("invalid_field", "id: expected a string of at most 128 bytes or an integer");
  }
  if (const msgpack::Value* key = field(req.root, "api_key")) {
    if (!key->is_str()) fail("invalid_field", "api_key: expected a string, got " + kind_of(*key));
    req.api_key = std::string(key->bytes);
  }
  if (const msgpack::Value* rid = field(req.root, "request_id")) {
    if (!rid->is_str()) fail("invalid_field", "request_id: expected a string, got " + kind_of(*rid));
    req.request_id = std::string(rid->bytes.substr(0, 256));
  }
  return req;
}

namespace {

// The /act fields of a msgpack map; `envelope`: api_key, request_id and id are accepted too (ZMQ carries them in the
// message, HTTP in its headers).
ActRequest decode_fields(const msgpack::Value& m, const models::ModelSpec& spec, bool envelope) {
  static const char* const kKnown[] = {"instruction", "state",   "image",      "images", "episode_id", "seed",
                                       "rtc",         "embodiment_tag", "api_key", "request_id", "id"};
  const std::size_t known_count = envelope ? std::size(kKnown) : std::size(kKnown) - 3;
  for (const auto& [k, _] : m.entries) {
    bool known = false;
    if (k.is_text_or_bin())
      for (std::size_t i = 0; i < known_count; ++i) known = known || k.bytes == kKnown[i];
    if (!known)
      fail("unknown_field", "unknown field '" + (k.is_text_or_bin() ? std::string(k.bytes.substr(0, 64)) : kind_of(k)) +
                                "' (accepted: " + (envelope ? kFields : kHttpFields) + ")");
  }
  ActRequest req;
  policy::Observation& obs = req.observation;
  const msgpack::Value* instruction = field(m, "instruction");
  if (!instruction) fail("missing_field", "'instruction' is required");
  if (!instruction->is_str()) fail("invalid_field", "instruction: expected a string, got " + kind_of(*instruction));
  obs.instruction = std::string(instruction->bytes);

  const msgpack::Value* state = field(m, "state");
  if (!state) fail("missing_field", "'state' is required (" + std::to_string(spec.state_dim) + " numbers)");
  obs.state = numbers(*state, "state");
  if (int64_t(obs.state.size()) != spec.state_dim)
    fail("invalid_state", "state has " + std::to_string(obs.state.size()) + " values, the model expects " +
                              std::to_string(spec.state_dim));

  const msgpack::Value* images = field(m, "images");
  const msgpack::Value* image = field(m, "image");
  if (images && image) fail("invalid_field", "give either 'image' (the first camera) or 'images', not both");
  if (!images && !image) fail("missing_field", "an image is required: 'images' {camera: image} or 'image'");
  if (image) {
    if (spec.cameras.empty()) fail("unknown_camera", "the model has no camera inputs");
    obs.images[spec.cameras.front()] = image_of(*image, "image");
  } else {
    if (!images->is_map()) fail("invalid_field", "images: expected a map {camera: image}, got " + kind_of(*images));
    if (images->entries.empty()) fail("missing_field", "images: at least one camera image is required");
    for (const auto& [k, v] : images->entries) {
      if (!k.is_text_or_bin()) fail("invalid_field", "images: camera names must be strings, got " + kind_of(k));
      const std::string name(k.bytes);
      const auto camera = resolve_camera(name, spec);
      if (!camera) {
        std::string known;
        for (const auto& c : spec.cameras) known += (known.empty() ? "" : ", ") + c;
        fail("unknown_camera", "images: the model has no camera '" + name.substr(0, 64) + "' (it has: " + known + ")");
      }
      if (obs.images.count(*camera)) fail("invalid_field", "images: camera '" + *camera + "' is given twice");
      obs.images[*camera] = image_of(v, "images." + name);
    }
  }
  if (const msgpack::Value* ep = field(m, "episode_id")) {
    if (!ep->is_str()) fail("invalid_field", "episode_id: expected a string, got " + kind_of(*ep));
    req.episode_id = std::string(ep->bytes);
  }
  if (const msgpack::Value* seed = field(m, "seed")) {
    if (seed->kind != msgpack::Kind::integer || (!seed->above_int64 && seed->integer < 0))
      fail("invalid_field", "seed: expected an integer >= 0");
    req.seed = seed->above_int64 ? seed->uinteger : uint64_t(seed->integer);
  }
  if (const msgpack::Value* rtc = field(m, "rtc")) req.rtc = rtc_of(*rtc, spec);
  if (const msgpack::Value* tag = field(m, "embodiment_tag")) {
    if (!tag->is_str()) fail("invalid_field", "embodiment_tag: expected a string, got " + kind_of(*tag));
    // The pipeline routed the request by this tag (embodiment_of) to the host whose spec this is.
    if (tag->bytes != spec.embodiment)
      fail("invalid_field", "embodiment_tag: '" + std::string(tag->bytes.substr(0, 64)) + "' is not the embodiment '" +
                                spec.embodiment + "' this request was decoded for");
    req.embodiment = spec.embodiment;
  }
  check_observation(obs, spec);
  return req;
}

}  // namespace

ActRequest decode_act(const Request& request, const models::ModelSpec& spec) {
  return decode_fields(request.root, spec, true);
}

ActRequest decode_message(std::string_view message, const models::ModelSpec& spec) {
  return decode_act(parse_request(message), spec);
}

std::string embodiment_of(const msgpack::Value& map) {
  const msgpack::Value* tag = map.is_map() ? field(map, "embodiment_tag") : nullptr;
  return tag && tag->is_str() ? std::string(tag->bytes) : std::string();
}

std::string http_body_embodiment(std::string_view body) {
  try {
    return embodiment_of(msgpack::parse_map(body, "body", "with /act's fields"));
  } catch (const std::exception&) {
    return "";  // decode_http_body reports it
  }
}

ActRequest decode_http_body(std::string_view body, const models::ModelSpec& spec) {
  return decode_fields(msgpack::parse_map(body, "body", "with /act's fields"), spec, false);
}

std::string encode_body(const Json& body) {
  msgpack::Writer w;
  w.map(uint32_t(body.size()));
  write_body(w, body);
  return w.take();
}

std::string encode_reply(int status, const Json& body, int retry_after_s, const std::string& request_id, const Json& id) {
  const bool has_request_id = !body.contains("request_id") && !request_id.empty();
  const bool retry = status == 503;
  msgpack::Writer w;
  w.map(uint32_t(body.size() + 1 + (has_request_id ? 1 : 0) + (retry ? 1 : 0) + (id.is_null() ? 0 : 1)));
  write_body(w, body);
  w.str("status");
  w.integer(status);
  if (has_request_id) {
    w.str("request_id");
    w.str(request_id);
  }
  if (retry) {
    w.str("retry_after_s");
    w.integer(retry_after_s);
  }
  if (!id.is_null()) {
    w.str("id");
    msgpack::write_json(w, id);
  }
  return w.take();
}

std::string error_reply(int status, const std::string& code, const std::string& message) {
  return encode_reply(status, Json{{"error", {{"code", code}, {"message", message}}}}, 1, "", Json());
}

}  // namespace tether::serve::zmqp
