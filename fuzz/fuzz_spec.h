// What the request decoders' fuzz harnesses share: the fake model spec they decode against, and the contract every
// decoder keeps (an observation the engine accepts, or a 400 with one of its documented codes, nothing else).
#pragma once

#include <cmath>
#include <cstring>
#include <initializer_list>
#include <string>

#include "models/model.h"
#include "serve/act_request.h"
#include "serve/http_error.h"

namespace tether::fuzz {

// Two cameras (front, wrist), a state and an action of 3 values, chunks of 4 rows.
inline const models::ModelSpec& fake_spec() {
  static const models::ModelSpec s = [] {
    models::ModelSpec m;
    m.family = "smolvla";
    m.cameras = {"observation.images.front", "observation.images.wrist"};
    m.camera_prefix = "observation.images.";
    m.state_key = "observation.state";
    m.action_key = "action";
    m.state_dim = 3;
    m.action_dim = 3;
    m.chunk_size = 4;
    return m;
  }();
  return s;
}

// Traps unless the decoded request is one the engine accepts: the spec's number of finite state values, at least one
// image, each of a camera the spec has and holding its height * width * 3 bytes.
inline void check_accepted(const serve::ActRequest& req) {
  const auto& obs = req.observation;
  if (int64_t(obs.state.size()) != fake_spec().state_dim || obs.images.empty()) __builtin_trap();
  for (float v : obs.state)
    if (!std::isfinite(v)) __builtin_trap();
  for (const auto& [camera, img] : obs.images) {
    if (!serve::resolve_camera(camera, fake_spec())) __builtin_trap();
    if (img.rgb.empty() || img.rgb.size() != std::size_t(img.height) * std::size_t(img.width) * 3) __builtin_trap();
  }
}

// Traps unless the refusal is a 400 with one of `codes` and a message.
inline void check_refusal(const serve::HttpError& e, std::initializer_list<const char*> codes) {
  if (e.status() != 400 || std::strlen(e.what()) == 0) __builtin_trap();
  for (const char* code : codes)
    if (e.code() == code) return;
  __builtin_trap();
}

// The contract of both msgpack /act decoders (a Tether ZMQ message, a POST /act msgpack body): `decode()` yields a
// well-formed request (a real-time chunking prefix of whole action rows) or a 400 with one of /act's codes.
template <class Decode>
void check_msgpack_act(Decode&& decode) {
  try {
    const serve::ActRequest req = decode();
    check_accepted(req);
    if (req.rtc && (req.rtc->rows < 1 || int64_t(req.rtc->prev_actions.size()) != req.rtc->rows * fake_spec().action_dim))
      __builtin_trap();
  } catch (const serve::HttpError& e) {
    check_refusal(e, {"bad_msgpack", "invalid_field", "invalid_state", "invalid_image", "unknown_camera",
                      "unknown_field", "missing_field"});
  }
}

}  // namespace tether::fuzz
