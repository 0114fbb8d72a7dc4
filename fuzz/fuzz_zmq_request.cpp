// libFuzzer target: any byte string as a Tether ZMQ request yields an ActRequest or an HttpError(400) with one of
// /act's codes (or bad_msgpack), nothing else.
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <string_view>

#include "serve/http_error.h"
#include "serve/zmq_protocol.h"

namespace {

const tether::models::ModelSpec& spec() {
  static const tether::models::ModelSpec s = [] {
    tether::models::ModelSpec m;
    m.family = "smolvla";
    m.cameras = {"observation.images.front", "observation.images.wrist"};
    m.camera_prefix = "observation.images.";
    m.state_dim = 3;
    m.action_dim = 3;
    m.chunk_size = 4;
    return m;
  }();
  return s;
}

bool known_code(const std::string& c) {
  for (const char* k : {"bad_msgpack", "invalid_field", "invalid_state", "invalid_image", "unknown_camera",
                        "unknown_field", "missing_field"})
    if (c == k) return true;
  return false;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace tether::serve;
  try {
    const ActRequest req = zmqp::decode_message(std::string_view(reinterpret_cast<const char*>(data), size), spec());
    const auto& obs = req.observation;
    if (int64_t(obs.state.size()) != spec().state_dim || obs.images.empty()) __builtin_trap();
    for (const auto& [camera, img] : obs.images)
      if (!resolve_camera(camera, spec()) || img.rgb.size() != std::size_t(img.height) * std::size_t(img.width) * 3 ||
          img.rgb.empty())
        __builtin_trap();
    if (req.rtc && (req.rtc->rows < 1 || int64_t(req.rtc->prev_actions.size()) != req.rtc->rows * spec().action_dim))
      __builtin_trap();
  } catch (const HttpError& e) {
    if (e.status() != 400 || !known_code(e.code()) || std::strlen(e.what()) == 0) __builtin_trap();
  }
  return 0;
}
