// openpi's WebSocket policy protocol without the socket: a msgpack-numpy observation frame to an ActRequest through an
// observation key layout (libero, droid, aloha or a mapping file), and the /act answer back to openpi's reply map.
// Pure functions of their inputs, so fuzz/fuzz_openpi_request.cpp can drive the decoder directly.
#pragma once

#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "core/json_util.h"
#include "models/model.h"
#include "serve/act_request.h"

namespace tether::serve::openpi {

// Which client key feeds which camera, which keys make up the state, and where the prompt is. A key inside a nested
// map is its path joined with '/': aloha's {"images": {"cam_high": ...}} is "images/cam_high".
struct Layout {
  struct Image {
    std::string key;     // the client's key
    std::string camera;  // the checkpoint camera it feeds (with or without the model's camera prefix)
  };
  std::string name;  // libero, droid, aloha, or the mapping file's path
  std::vector<Image> images;
  // Built-in layouts: a key whose camera name the checkpoint lacks feeds the next camera not claimed by name, in
  // model order; keys left over are ignored. A mapping file names its cameras exactly.
  bool fill_by_position = false;
  std::vector<std::string> state;  // concatenated in this order
  std::string prompt = "prompt";
  std::optional<std::string> default_prompt;  // used when the prompt key is absent
  std::vector<std::string> ignored;           // keys accepted and not read
};

// What --openpi-layout names: one layout, or several of which each request uses the one that reads all its keys.
struct Layouts {
  std::string name;  // as given: auto, libero, droid, aloha or the file's path
  std::vector<Layout> candidates;
};

// libero, droid and aloha as openpi's example clients send them.
std::vector<Layout> builtin_layouts();
// "auto" (every built-in layout, default), "libero", "droid", "aloha", or a path to a JSON mapping file. Throws
// tether::Error(invalid_argument) naming the file and field at fault.
Layouts load_layouts(const std::string& flag_value);
// A mapping file's text (docs/transports/openpi.md); `source` names it in errors.
Layout parse_layout_json(std::string_view text, const std::string& source);

// The checkpoint camera each of layout.images feeds (nullopt: the model lacks it; the key is then ignored). Throws
// HttpError(400, unknown_camera) for a mapping file naming a camera the model does not have.
std::vector<std::optional<std::string>> resolve_cameras(const Layout& layout, const models::ModelSpec& spec);

// Tether's extensions, read in every layout: an episode id (string) and a noise seed (non-negative integer).
inline constexpr std::string_view kEpisodeKey = "episode_id";
inline constexpr std::string_view kSeedKey = "seed";

// One request frame (a msgpack map, arrays in msgpack-numpy form with binary or string keys) to an ActRequest.
// Throws HttpError(400, code), code one of invalid_msgpack, invalid_field, invalid_image, invalid_state,
// unknown_field, unknown_camera, missing_field; the message names the key at fault.
ActRequest decode_request(std::string_view frame, const Layouts& layouts, const models::ModelSpec& spec);

// server_timing as openpi's server writes it: this request's time in the policy, and the previous request's total
// (receive to reply sent) on the same connection, absent for its first.
struct ServerTiming {
  double infer_ms = 0;
  std::optional<double> prev_total_ms;
};

// The reply to a successful /act answer `act_body`: {"actions": float32 [rows, dim] ndarray, "policy_timing":
// {"infer_ms"}, "server_timing": {...}, "tether": the rest of the answer (request_id, latency_ms, wedge fields)}.
// policy_timing.infer_ms is the forward pass (latency_ms.predict), 0 when none ran.
std::string encode_reply(const Json& act_body, const ServerTiming& timing);

// JSON as msgpack (objects as maps with string keys), for the metadata frame.
std::string encode_json(const Json& value);

// An array in msgpack-numpy form (binary keys __ndarray__, data, dtype, shape), as openpi_client's unpackb reads it.
std::string encode_float32_array(const std::vector<float>& values, const std::vector<int64_t>& shape);

}  // namespace tether::serve::openpi
