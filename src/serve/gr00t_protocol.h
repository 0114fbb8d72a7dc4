// Isaac-GR00T's ZMQ PolicyClient protocol, as pure functions: a request's bytes to an endpoint call and, for
// get_action, each batch item to an ActRequest; the replies back to bytes. Requests are msgpack maps
// {"endpoint", "data", "api_token"}; arrays travel as {"__ndarray_class__": true, "as_npy": <.npy bytes>} (parsed
// without pickle). See docs/transports/gr00t.md.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "core/json_util.h"
#include "models/model.h"
#include "serve/act_request.h"
#include "serve/msgpack.h"

namespace tether::serve::gr00t {

enum class Endpoint { ping, kill, get_action, reset, get_modality_config };

struct Call {
  Endpoint endpoint = Endpoint::get_action;  // upstream's default when the field is absent
  std::string api_token;                     // empty: none given
  msgpack::Value data;                       // the "data" map (nil when absent); views into the parsed message
};

// Throws HttpError(400): bad_msgpack (not msgpack, or not a map), invalid_field (a field of the wrong type),
// unknown_endpoint. `message` must outlive the Call.
Call parse_call(std::string_view message);

// How get_action's observation is laid out: nested {"video": {cam: ...}, "state": {...}, "language": {...}} (the
// Gr00tPolicy form: actions are answered as {group: ...}) or flat {"video.cam", "state.group", "task"} (the
// simulation wrapper's: actions are answered as {"action.group": ...}).
struct Layout {
  bool flat = false;
  int64_t batch = 1;  // B, from the first video (or state) array; 1 when it cannot be told (decode names the fault)
};
Layout observation_layout(const Call& call);

// Item `index` of get_action's batch as an ActRequest: the last frame of each video (B, T, H, W, 3) uint8, the last
// row of each state group (B, T, D_g), concatenated in the spec's group order (models::state_groups), the item's
// language instruction, and options.seed / options.episode_id (one value, or a list with one per item). Throws
// HttpError(400, code) naming the field or group: missing_field, invalid_field, invalid_state, unknown_camera,
// unknown_field.
ActRequest decode_item(const Call& call, int64_t index, const models::ModelSpec& spec);

// data.options.embodiment_tag: the embodiment a call is for (one per call; empty: the server's default). Throws
// HttpError(400, invalid_field) when it is not a string.
std::string call_embodiment(const Call& call);

// The episodes a reset call ends: data.options.episode_id (a string, or a list of strings), else the default episode
// "" that get_action calls without an episode_id share. Throws HttpError(400, invalid_field).
std::vector<std::string> reset_episodes(const Call& call);

// A camera's name on the wire: the checkpoint's key without spec.camera_prefix.
std::string camera_name(const std::string& key, const models::ModelSpec& spec);

// Replies, as upstream's PolicyServer shapes them.
std::string ping_reply();   // {"status": "ok", "message": "Server is running"}
std::string reset_reply();  // {}
std::string kill_reply();   // nil
// {"error": message, "code": code, "status": status}: upstream's client raises on the "error" key.
std::string error_reply(int status, const std::string& code, const std::string& message);
// {video, state, action, language}: each a {"__ModalityConfig_class__": true, "as_json": {delta_indices,
// modality_keys, ...}}, the state and action modality_keys being the groups in order, plus "tether": {cameras,
// state_dim, action_dim, state_groups, action_groups ([{name, dim}]), chunk_size, ...} (a plain map).
std::string modality_config_reply(const models::ModelSpec& spec, int64_t action_dim);
// [ {group: float32 array (B, rows, dim_g)} for each action group, info ]: `actions` (B * rows * dim values, dim the
// sum of the groups' dims) split by column into the groups, keyed "action.<group>" when `flat`; info is
// {"tether": items}. Groups that do not add up to `dim` give an internal_error reply instead.
std::string action_reply(const std::vector<models::ModalityGroup>& groups, bool flat, int64_t batch, int64_t rows,
                         int64_t dim, const std::vector<float>& actions, const Json& items);

// {"__ndarray_class__": true, "as_npy": npy} for an array, as upstream's MsgSerializer writes numpy arrays.
void write_ndarray(msgpack::Writer& w, const std::string& npy);

}  // namespace tether::serve::gr00t
