// Tether's own ZMQ protocol, as pure functions: a msgpack map with /act's fields (images as PNG/JPEG bytes or raw
// {"data": bin, "shape": [H, W, 3]}) plus "api_key", "request_id" and "id" (echoed verbatim, so a DEALER client can
// match replies), and the reply: /act's answer as a msgpack map, with "status". See docs/transports/zmq.md.
#pragma once

#include <string>
#include <string_view>

#include "core/json_util.h"
#include "models/model.h"
#include "serve/act_request.h"
#include "serve/msgpack.h"

namespace tether::serve::zmqp {

struct Request {
  msgpack::Value root;     // the whole map; views into the message, which must outlive it
  std::string api_key;     // empty: none
  std::string request_id;  // the client's suggestion (used when valid, see request_id_or_new); empty: none
  Json id;                 // the client's "id" (a string or an integer), null when absent
};

// The envelope only: msgpack map, api_key, request_id, id. Throws HttpError(400, bad_msgpack / invalid_field).
Request parse_request(std::string_view message);

// The /act fields of a parsed request (instruction, state, image or images, episode_id, seed, rtc). Throws
// HttpError(400, code) with /act's codes: missing_field, invalid_field, invalid_state, invalid_image, unknown_camera,
// unknown_field.
ActRequest decode_act(const Request& request, const models::ModelSpec& spec);

// Bytes to ActRequest in one step (the fuzz target's entry).
ActRequest decode_message(std::string_view message, const models::ModelSpec& spec);

// A POST /act body sent as Content-Type: application/msgpack: the same map without the envelope fields (api_key,
// request_id and id travel as HTTP headers there, and are refused as unknown_field). Throws HttpError(400,
// bad_msgpack) for bytes that are not one msgpack map, else decode_act's codes.
ActRequest decode_http_body(std::string_view body, const models::ModelSpec& spec);

// The "embodiment_tag" string of a request map (ActInput::embodiment routes by it); empty when absent or not a
// string (decode_act then refuses it). http_body_embodiment: the same for an HTTP msgpack body, empty when the body
// does not parse.
std::string embodiment_of(const msgpack::Value& map);
std::string http_body_embodiment(std::string_view body);

// The /act answer (or {"error": {...}}) as a msgpack map, `actions` rows as float32 arrays: HTTP's msgpack answer.
std::string encode_body(const Json& body);

// A reply: `body` (the /act answer or {"error": {code, message}}) as a map, `actions` rows as float32 arrays, plus
// "status", "request_id", "retry_after_s" on a 503, and "id" when the request had one.
std::string encode_reply(int status, const Json& body, int retry_after_s, const std::string& request_id, const Json& id);

// An error reply for a message that could not be read at all.
std::string error_reply(int status, const std::string& code, const std::string& message);

}  // namespace tether::serve::zmqp
