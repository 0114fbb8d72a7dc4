// The body of POST /act: JSON to an Observation, with every check of the API contract done here, before the request
// can reach a batch (one malformed request must never fail the requests it would have been batched with).
#pragma once

#include <optional>
#include <string>
#include <string_view>

#include "models/model.h"
#include "policy/policy.h"
#include "serve/http_error.h"
#include "vision/image.h"

namespace tether::serve {

// Real-time chunking inputs: the previous chunk's actions not yet executed (robot units) and how many of them will
// still run while this request is computed.
struct RtcFields {
  std::vector<float> prev_actions;  // [rows, action_dim]
  int64_t rows = 0;
  int inference_delay = 0;
};

struct ActRequest {
  policy::Observation observation;      // images keyed by the checkpoint's camera names
  std::optional<uint64_t> seed;         // absent: the server derives one from the request id
  std::optional<std::string> episode_id;
  std::optional<RtcFields> rtc;
  std::string embodiment;  // the GR00T embodiment tag the request named (empty: the server's default)
};


// Deepest JSON nesting accepted: the schema needs 4; the cap keeps hostile input from exhausting the stack.
inline constexpr int kMaxJsonDepth = 16;

// The "embodiment_tag" string of an /act body, for routing before decoding; empty when absent, not a string, or the
// body not a JSON object (parse_act_request then reports what is wrong).
std::string act_request_embodiment(std::string_view body);

// Throws HttpError(400, code) with code one of bad_json, invalid_field, invalid_state, invalid_image,
// unknown_camera, unknown_field, missing_field; the message names the field at fault.
ActRequest parse_act_request(std::string_view body, const models::ModelSpec& spec);

// The checks of the API contract that do not depend on the wire format, for transports that decode their own
// (msgpack, npy, KServe tensors): `state` has spec.state_dim finite values, and at least one camera image is given.
// Throws HttpError(400, invalid_state / missing_field).
void check_observation(const policy::Observation& obs, const models::ModelSpec& spec);

// A raw uint8 RGB image [height, width, 3] (row-major, `data` holds height*width*3 bytes) as `field` of a request:
// dimensions checked against vision::kMaxImagePixels (HttpError(400, invalid_field) naming the field).
vision::Image raw_rgb_image(const uint8_t* data, int64_t height, int64_t width, const std::string& field);

// `req` as a POST /act body (images in the raw {"data", "shape"} form), so a request that came in on another
// transport can be forwarded to a cloud fallback, which speaks /act.
std::string act_request_json(const ActRequest& req);

// The camera key `name` stands for (the key, or the key without spec.camera_prefix: "front" ->
// "observation.images.front"); nullopt for a camera the model does not have.
std::optional<std::string> resolve_camera(const std::string& name, const models::ModelSpec& spec);

}  // namespace tether::serve
