// Open Inference Protocol v2 decoding and encoding: tensors checked by name, datatype, shape and data length, each
// failure a 400 naming the tensor; binary tensor data little-endian, BYTES elements as a 4-byte length and the bytes.
#include "serve/kserve_protocol.h"

#include <bit>
#include <cstring>
#include <limits>
#include <map>

#include "text/unicode.h"

namespace tether::serve::kserve {

static_assert(std::endian::native == std::endian::little, "binary tensor data is little-endian, as is the host");

namespace {

using J = nlohmann::json;  // request key order carries no meaning

[[noreturn]] void fail(const std::string& code, const std::string& message) { throw HttpError(400, code, message); }

std::string shape_text(const std::vector<int64_t>& shape) {
  std::string s = "[";
  for (std::size_t i = 0; i < shape.size(); ++i) s += (i ? ", " : "") + std::to_string(shape[i]);
  return s + "]";
}

std::size_t element_size(const std::string& datatype) {
  static const std::map<std::string, std::size_t> sizes = {
      {"BOOL", 1}, {"UINT8", 1}, {"UINT16", 2}, {"UINT32", 4}, {"UINT64", 8}, {"INT8", 1},  {"INT16", 2},
      {"INT32", 4}, {"INT64", 8}, {"FP16", 2},  {"FP32", 4},   {"FP64", 8},   {"BF16", 2}, {"BYTES", 0}};
  const auto it = sizes.find(datatype);
  return it == sizes.end() ? std::size_t(-1) : it->second;
}

J parse_header(std::string_view text) {
  auto depth_guard = [](int depth, J::parse_event_t, J&) {
    if (depth > kMaxJsonDepth)
      throw HttpError(400, "bad_json", "the inference request nests JSON deeper than " + std::to_string(kMaxJsonDepth) +
                                           " levels");
    return true;
  };
  try {
    return J::parse(text.begin(), text.end(), depth_guard);
  } catch (const HttpError&) {
    throw;
  } catch (const J::exception& e) {
    fail("bad_json", std::string("the inference request header is not valid JSON: ") + e.what());
  }
}

// The role a named input plays.
enum class Role { instruction, state, image, seed, episode_id };

struct Input {
  Role role;
  std::string name;  // as the request names it
  std::string camera;  // Role::image: the checkpoint's key
  std::string datatype;
  std::vector<int64_t> shape;
  uint64_t count = 0;  // elements
  // The data, by datatype: BYTES -> strings; FP32 -> floats; UINT8 -> bytes (a view of the binary tail, or owned);
  // INT64 / UINT64 -> integers (negative INT64 refused).
  std::vector<std::string> strings;
  std::vector<float> floats;
  std::string owned_bytes;  // from JSON data
  std::string_view tail_bytes;  // from binary data (a view of the body)
  bool owned = false;
  std::vector<uint64_t> integers;
  const uint8_t* pixels() const {
    return reinterpret_cast<const uint8_t*>(owned ? owned_bytes.data() : tail_bytes.data());
  }
};

std::string known_inputs(const models::ModelSpec& spec) {
  std::string s = std::string(kInstruction) + ", " + kState;
  for (const auto& c : spec.cameras) s += ", " + image_tensor_name(c, spec);
  return s + ", " + kSeed + ", " + kEpisodeId;
}

Input identify(const std::string& name, const models::ModelSpec& spec) {
  Input in;
  in.name = name;
  if (name == kInstruction) in.role = Role::instruction;
  else if (name == kState) in.role = Role::state;
  else if (name == kSeed) in.role = Role::seed;
  else if (name == kEpisodeId) in.role = Role::episode_id;
  else if (name.rfind(kImagePrefix, 0) == 0) {
    const auto camera = resolve_camera(name.substr(std::strlen(kImagePrefix)), spec);
    if (!camera)
      fail("unknown_camera", "input '" + name + "': the model has no such camera (its inputs: " + known_inputs(spec) + ")");
    in.role = Role::image;
    in.camera = *camera;
  } else {
    fail("unknown_field", "unknown input tensor '" + name + "' (the model takes: " + known_inputs(spec) + ")");
  }
  return in;
}

void check_datatype(const Input& in) {
  const std::string& dt = in.datatype;
  const char* want = nullptr;
  switch (in.role) {
    case Role::instruction:
    case Role::episode_id: want = "BYTES"; break;
    case Role::state: want = "FP32"; break;
    case Role::image: want = "UINT8"; break;
    case Role::seed:
      if (dt == "INT64" || dt == "UINT64") return;
      want = "INT64 or UINT64";
      break;
  }
  if (dt != want) {
    const bool known = element_size(dt) != std::size_t(-1);
    fail("invalid_field", "input '" + in.name + "': datatype '" + dt + "'" + (known ? "" : " is not a v2 datatype;") +
                              " expected " + want);
  }
}

// Checks the shape against the role; returns the batch size it gives.
int64_t check_shape(const Input& in, const models::ModelSpec& spec) {
  const auto& s = in.shape;
  const auto bad = [&](const std::string& expected) {
    fail(in.role == Role::state && s.size() == 2 ? "invalid_state" : "invalid_field",
         "input '" + in.name + "': shape " + shape_text(s) + ", expected " + expected);
  };
  switch (in.role) {
    case Role::instruction:
    case Role::seed:
    case Role::episode_id:
      if (!(s.size() == 1 || (s.size() == 2 && s[1] == 1))) bad("[B] or [B, 1]");
      break;
    case Role::state:
      if (s.size() != 2 || s[1] != spec.state_dim) bad("[B, " + std::to_string(spec.state_dim) + "] (state_dim " +
                                                       std::to_string(spec.state_dim) + ")");
      break;
    case Role::image:
      if (s.size() != 4 || s[3] != 3 || s[1] < 1 || s[2] < 1) bad("[B, H, W, 3] (uint8 RGB, H and W at least 1)");
      if (s[1] > vision::kMaxImagePixels / s[2])
        fail("invalid_field", "input '" + in.name + "': " + std::to_string(s[1]) + "x" + std::to_string(s[2]) +
                                  " exceeds the " + std::to_string(vision::kMaxImagePixels) + "-pixel limit");
      break;
  }
  if (s[0] < 1) fail("invalid_field", "input '" + in.name + "': shape " + shape_text(s) + " has no batch items");
  if (s[0] > kMaxBatchItems)
    fail("invalid_field", "input '" + in.name + "': a batch of " + std::to_string(s[0]) + " items; at most " +
                              std::to_string(kMaxBatchItems) + " per request");
  return s[0];
}

std::vector<int64_t> parse_shape(const J& v, const std::string& name) {
  if (!v.is_array()) fail("invalid_field", "input '" + name + "': 'shape' must be an array of integers");
  if (v.size() > 8) fail("invalid_field", "input '" + name + "': 'shape' has " + std::to_string(v.size()) + " dimensions");
  std::vector<int64_t> shape;
  for (const J& d : v) {
    // Each dimension fits an unsigned 64-bit integer (the spec); more than 2^40 is no real tensor.
    if (!d.is_number_integer() || (d.is_number_integer() && !d.is_number_unsigned() && d.get<int64_t>() < 0) ||
        d.get<uint64_t>() > (uint64_t(1) << 40))
      fail("invalid_field", "input '" + name + "': 'shape' dimensions must be integers >= 0, got " + d.dump());
    shape.push_back(d.get<int64_t>());
  }
  return shape;
}

// The element count of `shape`; refuses counts no request body could carry.
uint64_t element_count(const std::vector<int64_t>& shape, const std::string& name) {
  uint64_t n = 1;
  for (int64_t d : shape) {
    if (d != 0 && n > (uint64_t(1) << 40) / uint64_t(d))
      fail("invalid_field", "input '" + name + "': shape " + shape_text(shape) + " has too many elements");
    n *= uint64_t(d);
  }
  return n;
}

// Flattens `data` (flat or nested lists) into `out`, refusing more than `limit` elements.
void flatten(const J& data, std::vector<const J*>& out, uint64_t limit, const std::string& name) {
  if (!data.is_array()) {
    if (out.size() >= limit)
      fail("invalid_field", "input '" + name + "': 'data' has more elements than its shape's " + std::to_string(limit));
    out.push_back(&data);
    return;
  }
  for (const J& e : data) flatten(e, out, limit, name);
}

void check_utf8(const std::string& s, const std::string& where) {
  const std::size_t bad = text::find_invalid_utf8(s);
  if (bad != std::string_view::npos)
    fail("invalid_field", where + ": not valid UTF-8 (at byte " + std::to_string(bad) + ")");
}

void read_json_data(Input& in, const J& data) {
  if (!data.is_array()) fail("invalid_field", "input '" + in.name + "': 'data' must be a JSON array");
  std::vector<const J*> flat;
  flatten(data, flat, in.count, in.name);
  if (flat.size() != in.count)
    fail("invalid_field", "input '" + in.name + "': 'data' has " + std::to_string(flat.size()) + " elements, shape " +
                              shape_text(in.shape) + " needs " + std::to_string(in.count));
  const auto element_error = [&](std::size_t i, const char* expected) {
    fail("invalid_field", "input '" + in.name + "': data[" + std::to_string(i) + "] is " + flat[i]->dump() +
                              ", expected " + expected);
  };
  for (std::size_t i = 0; i < flat.size(); ++i) {
    const J& e = *flat[i];
    if (in.datatype == "BYTES") {
      if (!e.is_string()) element_error(i, "a string");
      in.strings.push_back(e.get<std::string>());
    } else if (in.datatype == "FP32") {
      if (!e.is_number()) element_error(i, "a number");
      in.floats.push_back(float(e.get<double>()));
    } else if (in.datatype == "UINT8") {
      if (!e.is_number_integer() || (!e.is_number_unsigned() && e.get<int64_t>() < 0) || e.get<uint64_t>() > 255)
        element_error(i, "an integer from 0 to 255");
      in.owned_bytes.push_back(char(e.get<uint64_t>()));
    } else if (in.datatype == "UINT64") {
      if (!e.is_number_integer() || (!e.is_number_unsigned() && e.get<int64_t>() < 0)) element_error(i, "an integer >= 0");
      in.integers.push_back(e.get<uint64_t>());
    } else {  // INT64
      if (!e.is_number_integer() || (!e.is_number_unsigned() && e.get<int64_t>() < 0) ||
          (e.is_number_unsigned() && e.get<uint64_t>() > uint64_t(std::numeric_limits<int64_t>::max())))
        element_error(i, "an integer from 0 to 2^63-1 (a seed is never negative)");
      in.integers.push_back(e.get<uint64_t>());
    }
  }
  in.owned = true;
}

void read_binary_data(Input& in, std::string_view data) {
  if (in.datatype == "BYTES") {
    std::size_t at = 0;
    for (uint64_t i = 0; i < in.count; ++i) {
      if (data.size() - at < 4)
        fail("invalid_field", "input '" + in.name + "': binary data ends inside element " + std::to_string(i) +
                                  "'s 4-byte length (" + std::to_string(data.size()) + " bytes for " +
                                  std::to_string(in.count) + " elements)");
      uint32_t len;
      std::memcpy(&len, data.data() + at, 4);
      at += 4;
      if (data.size() - at < len)
        fail("invalid_field", "input '" + in.name + "': element " + std::to_string(i) + " declares " +
                                  std::to_string(len) + " bytes, only " + std::to_string(data.size() - at) + " are left");
      in.strings.emplace_back(data.substr(at, len));
      at += len;
    }
    if (at != data.size())
      fail("invalid_field", "input '" + in.name + "': binary_data_size " + std::to_string(data.size()) + " but its " +
                                std::to_string(in.count) + " elements take " + std::to_string(at) + " bytes");
    return;
  }
  const std::size_t size = element_size(in.datatype);
  if (uint64_t(data.size()) != in.count * size)
    fail("invalid_field", "input '" + in.name + "': binary_data_size " + std::to_string(data.size()) + ", shape " +
                              shape_text(in.shape) + " of " + in.datatype + " needs " + std::to_string(in.count * size) +
                              " bytes");
  if (in.datatype == "UINT8") {
    in.tail_bytes = data;
  } else if (in.datatype == "FP32") {
    in.floats.resize(in.count);
    std::memcpy(in.floats.data(), data.data(), data.size());
  } else {  // INT64 or UINT64
    in.integers.resize(in.count);
    std::memcpy(in.integers.data(), data.data(), data.size());
    if (in.datatype == "INT64")
      for (uint64_t i = 0; i < in.count; ++i)
        if (int64_t(in.integers[i]) < 0)
          fail("invalid_field", "input '" + in.name + "': element " + std::to_string(i) + " is negative (a seed is >= 0)");
  }
}

const J* find_parameters(const J& obj, const std::string& where) {
  const auto it = obj.find("parameters");
  if (it == obj.end() || it->is_null()) return nullptr;
  if (!it->is_object()) fail("invalid_field", where + ": 'parameters' must be an object");
  return &*it;
}

std::optional<bool> bool_parameter(const J* params, const char* key, const std::string& where) {
  if (!params) return std::nullopt;
  const auto it = params->find(key);
  if (it == params->end() || it->is_null()) return std::nullopt;
  if (!it->is_boolean()) fail("invalid_field", where + ": parameter '" + key + "' must be true or false");
  return it->get<bool>();
}

void refuse_shared_memory(const J* params, const std::string& where) {
  if (params && params->contains("shared_memory_region"))
    fail("invalid_field", where + ": shared memory is not supported (send the data in the request)");
}

std::vector<RequestedOutput> decode_outputs(const J& request, bool binary_default) {
  std::vector<RequestedOutput> outputs;
  const auto it = request.find("outputs");
  if (it != request.end() && !it->is_null()) {
    if (!it->is_array()) fail("invalid_field", "'outputs' must be an array");
    for (std::size_t i = 0; i < it->size(); ++i) {
      const J& o = (*it)[i];
      const std::string where = "outputs[" + std::to_string(i) + "]";
      if (!o.is_object() || !o.contains("name") || !o["name"].is_string())
        fail("invalid_field", where + ": expected {\"name\": ...}");
      const std::string name = o["name"].get<std::string>();
      if (name != kActions && name != kActionSource)
        fail("unknown_field", "unknown output tensor '" + name + "' (the model gives: " + kActions + ", " +
                                  kActionSource + ")");
      for (const auto& prev : outputs)
        if (prev.name == name) fail("invalid_field", "output '" + name + "' is requested twice");
      const J* params = find_parameters(o, "output '" + name + "'");
      refuse_shared_memory(params, "output '" + name + "'");
      if (params && params->contains("classification") && !(*params)["classification"].is_null() &&
          (*params)["classification"] != 0)
        fail("invalid_field", "output '" + name + "': the classification extension is not supported");
      outputs.push_back({name, bool_parameter(params, "binary_data", "output '" + name + "'").value_or(binary_default)});
    }
  }
  if (outputs.empty()) outputs = {{kActions, binary_default}, {kActionSource, binary_default}};
  return outputs;
}

}  // namespace

std::string image_tensor_name(const std::string& camera, const models::ModelSpec& spec) {
  const std::string& p = spec.camera_prefix;
  const bool prefixed = !p.empty() && camera.size() > p.size() && camera.compare(0, p.size(), p) == 0;
  return kImagePrefix + (prefixed ? camera.substr(p.size()) : camera);
}

InferRequest decode_infer_request(std::string_view body, std::string_view header_length,
                                  const models::ModelSpec& spec) {
  return decode_infer_request(body, header_length, [&spec](const std::string&) -> const models::ModelSpec& { return spec; });
}

InferRequest decode_infer_request(std::string_view body, std::string_view header_length, const SpecFor& spec_for) {
  std::size_t json_size = body.size();
  const bool has_binary = !header_length.empty();
  if (has_binary) {
    uint64_t n = 0;
    for (char c : header_length) {
      if (c < '0' || c > '9' || n > body.size())
        fail("invalid_field", "Inference-Header-Content-Length '" + std::string(header_length.substr(0, 32)) +
                                  "' is not a byte count");
      n = n * 10 + uint64_t(c - '0');
    }
    if (n > body.size())
      fail("invalid_field", "Inference-Header-Content-Length " + std::to_string(n) + " exceeds the body's " +
                                std::to_string(body.size()) + " bytes");
    json_size = std::size_t(n);
  }
  const J request = parse_header(body.substr(0, json_size));
  std::string_view tail = body.substr(json_size);
  if (!request.is_object()) fail("bad_json", "the inference request must be a JSON object, got " + std::string(request.type_name()));

  InferRequest out;
  const auto id = request.find("id");
  if (id != request.end() && !id->is_null()) {
    if (!id->is_string()) fail("invalid_field", "'id' must be a string");
    out.id = id->get<std::string>();
  }
  const J* params = find_parameters(request, "the request");
  const bool binary_output = bool_parameter(params, "binary_data_output", "the request").value_or(false);
  if (params && params->contains("embodiment_tag")) {
    const J& tag = params->at("embodiment_tag");
    if (!tag.is_string()) fail("invalid_field", "the request: parameters.embodiment_tag must be a string");
    out.embodiment = tag.get<std::string>();
  }
  const models::ModelSpec& spec = spec_for(out.embodiment);
  if (!out.embodiment.empty() && out.embodiment != spec.embodiment)
    fail("invalid_field", "the request: parameters.embodiment_tag '" + out.embodiment + "' is not the embodiment '" +
                              spec.embodiment + "' it was decoded for");

  const auto inputs_it = request.find("inputs");
  if (inputs_it == request.end() || !inputs_it->is_array() || inputs_it->empty())
    fail("missing_field", "'inputs' must be a non-empty array of input tensors (the model takes: " + known_inputs(spec) + ")");

  std::vector<Input> inputs;
  std::size_t tail_at = 0;
  int64_t batch = -1;
  std::string batch_from;
  for (std::size_t i = 0; i < inputs_it->size(); ++i) {
    const J& t = (*inputs_it)[i];
    if (!t.is_object() || !t.contains("name") || !t["name"].is_string())
      fail("invalid_field", "inputs[" + std::to_string(i) + "]: expected {\"name\", \"shape\", \"datatype\", \"data\"}");
    Input in = identify(t["name"].get<std::string>(), spec);
    const std::string where = "input '" + in.name + "'";
    for (const auto& prev : inputs)
      if (prev.role == in.role && prev.camera == in.camera)
        fail("invalid_field", where + ": given twice" + (in.role == Role::image ? " (camera " + in.camera + ")" : ""));
    const auto dt = t.find("datatype");
    if (dt == t.end() || !dt->is_string()) fail("invalid_field", where + ": 'datatype' must be a string");
    in.datatype = dt->get<std::string>();
    check_datatype(in);
    const auto shape = t.find("shape");
    if (shape == t.end()) fail("invalid_field", where + ": 'shape' is required");
    in.shape = parse_shape(*shape, in.name);
    if (in.shape.empty()) fail("invalid_field", where + ": shape [] has no batch dimension");
    const int64_t b = check_shape(in, spec);
    if (batch < 0) {
      batch = b;
      batch_from = in.name;
    } else if (b != batch) {
      fail("invalid_field", where + ": batch size " + std::to_string(b) + ", but input '" + batch_from + "' has " +
                                std::to_string(batch));
    }
    in.count = element_count(in.shape, in.name);

    const J* tparams = find_parameters(t, where);
    refuse_shared_memory(tparams, where);
    const auto data = t.find("data");
    const bool has_data = data != t.end() && !data->is_null();
    const bool has_size = tparams && tparams->contains("binary_data_size") && !(*tparams)["binary_data_size"].is_null();
    if (has_data && has_size) fail("invalid_field", where + ": both 'data' and parameters.binary_data_size");
    if (has_size) {
      const J& size = (*tparams)["binary_data_size"];
      if (!size.is_number_integer() || (!size.is_number_unsigned() && size.get<int64_t>() < 0))
        fail("invalid_field", where + ": parameters.binary_data_size must be an integer >= 0");
      if (!has_binary)
        fail("invalid_field", where + ": binary_data_size given, but the request has no Inference-Header-Content-Length "
                                      "header (the binary data must follow the JSON header)");
      const uint64_t n = size.get<uint64_t>();
      if (n > tail.size() - tail_at)
        fail("invalid_field", where + ": binary_data_size " + std::to_string(n) + ", but only " +
                                  std::to_string(tail.size() - tail_at) + " bytes of binary data are left (truncated)");
      read_binary_data(in, tail.substr(tail_at, std::size_t(n)));
      tail_at += std::size_t(n);
    } else if (has_data) {
      read_json_data(in, *data);
    } else {
      fail("invalid_field", where + ": no 'data' and no parameters.binary_data_size");
    }
    inputs.push_back(std::move(in));
  }
  if (tail_at != tail.size())
    fail("invalid_field", std::to_string(tail.size() - tail_at) + " bytes of binary data follow the inputs' "
                                                                  "binary_data_size (the sizes do not add up)");

  const auto find = [&](Role r) -> const Input* {
    for (const auto& in : inputs)
      if (in.role == r) return &in;
    return nullptr;
  };
  const Input* instruction = find(Role::instruction);
  const Input* state = find(Role::state);
  const Input* seed = find(Role::seed);
  const Input* episode = find(Role::episode_id);
  if (!instruction) fail("missing_field", "input 'instruction' (BYTES [B]) is required");
  if (!state) fail("missing_field", "input 'state' (FP32 [B, " + std::to_string(spec.state_dim) + "]) is required");
  bool any_image = false;
  for (const auto& in : inputs) any_image = any_image || in.role == Role::image;
  if (!any_image)
    fail("missing_field", "an image input is required (UINT8 [B, H, W, 3]; the model's: " +
                              (spec.cameras.empty() ? std::string("none") : image_tensor_name(spec.cameras[0], spec)) +
                              (spec.cameras.size() > 1 ? ", ..." : "") + ")");
  for (const auto& s : instruction->strings) check_utf8(s, "input 'instruction'");
  if (episode)
    for (const auto& s : episode->strings) check_utf8(s, "input 'episode_id'");

  const auto d = std::size_t(spec.state_dim);
  for (int64_t b = 0; b < batch; ++b) {
    const auto k = std::size_t(b);
    ActRequest req;
    req.embodiment = out.embodiment;
    policy::Observation& obs = req.observation;
    obs.instruction = instruction->strings[k];
    obs.state.assign(state->floats.begin() + std::ptrdiff_t(k * d), state->floats.begin() + std::ptrdiff_t((k + 1) * d));
    for (const auto& in : inputs) {
      if (in.role != Role::image) continue;
      const std::size_t per_item = std::size_t(in.shape[1] * in.shape[2] * 3);
      obs.images[in.camera] = raw_rgb_image(in.pixels() + k * per_item,
                                            in.shape[1], in.shape[2], "input '" + in.name + "'");
    }
    if (seed) req.seed = seed->integers[k];
    if (episode) req.episode_id = episode->strings[k];
    try {
      check_observation(obs, spec);
    } catch (const HttpError& e) {
      if (batch == 1) throw;
      throw HttpError(e.status(), e.code(), "item " + std::to_string(b) + ": " + e.what());
    }
    out.items.push_back(std::move(req));
  }
  out.outputs = decode_outputs(request, binary_output);
  return out;
}

EncodedResponse encode_infer_response(const std::string& model_name, const InferRequest& req,
                                      const std::vector<ItemAnswer>& items) {
  const int64_t batch = int64_t(items.size());
  const int64_t rows = items.empty() ? 0 : items[0].rows, dim = items.empty() ? 0 : items[0].dim;
  for (std::size_t i = 0; i < items.size(); ++i)
    if (items[i].rows != rows || items[i].dim != dim || int64_t(items[i].actions.size()) != rows * dim)
      throw HttpError(500, "internal_error",
                      "item " + std::to_string(i) + " answered a " + std::to_string(items[i].rows) + "x" +
                          std::to_string(items[i].dim) + " chunk, item 0 a " + std::to_string(rows) + "x" +
                          std::to_string(dim) + " one: no single 'actions' tensor holds both");
  Json outputs = Json::array();
  std::string tail;
  for (const auto& o : req.outputs) {
    Json t = {{"name", o.name}};
    if (o.name == kActions) {
      t["datatype"] = "FP32";
      t["shape"] = {batch, rows, dim};
      if (o.binary) {
        const std::size_t before = tail.size();
        for (const auto& item : items)
          tail.append(reinterpret_cast<const char*>(item.actions.data()), item.actions.size() * sizeof(float));
        t["parameters"] = {{"binary_data_size", tail.size() - before}};
      } else {
        Json data = Json::array();
        for (const auto& item : items)
          for (float v : item.actions) data.push_back(v);
        t["data"] = std::move(data);
      }
    } else {  // kActionSource
      t["datatype"] = "BYTES";
      t["shape"] = {batch};
      if (o.binary) {
        const std::size_t before = tail.size();
        for (const auto& item : items) {
          const auto len = uint32_t(item.action_source.size());
          tail.append(reinterpret_cast<const char*>(&len), 4);
          tail += item.action_source;
        }
        t["parameters"] = {{"binary_data_size", tail.size() - before}};
      } else {
        Json data = Json::array();
        for (const auto& item : items) data.push_back(item.action_source);
        t["data"] = std::move(data);
      }
    }
    outputs.push_back(std::move(t));
  }
  Json res = {{"model_name", model_name}, {"model_version", kModelVersion}};
  if (req.id) res["id"] = *req.id;
  // Timing as scalar parameters (v2 allows only strings, numbers and booleans there): the server's time for the
  // request and the forward pass's, so a client can tell the transport's share from the model's.
  double total_ms = 0, predict_ms = 0;
  for (const auto& item : items) {
    total_ms = std::max(total_ms, item.total_ms);
    predict_ms = std::max(predict_ms, item.predict_ms);
  }
  res["parameters"] = {{"tether_total_ms", total_ms}, {"tether_predict_ms", predict_ms}};
  res["outputs"] = std::move(outputs);
  EncodedResponse enc;
  enc.body = res.dump(-1, ' ', false, Json::error_handler_t::replace);
  bool any_binary = false;
  for (const auto& o : req.outputs) any_binary = any_binary || o.binary;
  if (any_binary) {
    enc.header_length = enc.body.size();
    enc.body += tail;
  }
  return enc;
}

Json model_metadata(const std::string& name, const models::ModelSpec& spec, int64_t action_dim) {
  const auto tensor = [](const std::string& n, const char* datatype, std::vector<int64_t> shape) {
    return Json{{"name", n}, {"datatype", datatype}, {"shape", std::move(shape)}};
  };
  Json inputs = Json::array();
  inputs.push_back(tensor(kInstruction, "BYTES", {-1}));
  inputs.push_back(tensor(kState, "FP32", {-1, spec.state_dim}));
  for (const auto& c : spec.cameras) inputs.push_back(tensor(image_tensor_name(c, spec), "UINT8", {-1, -1, -1, 3}));
  inputs.push_back(tensor(kSeed, "INT64", {-1}));
  inputs.push_back(tensor(kEpisodeId, "BYTES", {-1}));
  Json outputs = Json::array();
  outputs.push_back(tensor(kActions, "FP32", {-1, spec.chunk_size, action_dim}));
  outputs.push_back(tensor(kActionSource, "BYTES", {-1}));
  return {{"name", name},
          {"versions", {kModelVersion}},
          {"platform", "tether_" + spec.family},
          {"inputs", std::move(inputs)},
          {"outputs", std::move(outputs)}};
}

Json server_metadata(const std::string& version) {
  return {{"name", "tether"}, {"version", version}, {"extensions", {kBinaryExtension}}};
}

Json error_json(const std::string& message) { return {{"error", message}}; }

}  // namespace tether::serve::kserve
