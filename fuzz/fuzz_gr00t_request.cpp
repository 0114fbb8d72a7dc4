// libFuzzer target: any byte string as a GR00T ZMQ request yields an endpoint call (and, for get_action, ActRequests
// for its batch items) or an HttpError(400) with a known code, nothing else.
#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <string_view>

#include "serve/gr00t_protocol.h"
#include "serve/http_error.h"

namespace {

const tether::models::ModelSpec& spec() {
  static const tether::models::ModelSpec s = [] {
    tether::models::ModelSpec m;
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

bool known_code(const std::string& c) {
  for (const char* k : {"bad_msgpack", "invalid_field", "invalid_state", "unknown_camera", "unknown_field",
                        "missing_field", "unknown_endpoint"})
    if (c == k) return true;
  return false;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace tether::serve;
  try {
    const gr00t::Call call = gr00t::parse_call(std::string_view(reinterpret_cast<const char*>(data), size));
    if (call.endpoint != gr00t::Endpoint::get_action) return 0;
    const gr00t::Layout layout = gr00t::observation_layout(call);
    if (layout.batch < 1) __builtin_trap();
    for (int64_t i = 0; i < std::min<int64_t>(layout.batch, 4); ++i) {
      const ActRequest req = gr00t::decode_item(call, i, spec());
      const auto& obs = req.observation;
      if (int64_t(obs.state.size()) != spec().state_dim || obs.images.empty()) __builtin_trap();
      for (const auto& [camera, img] : obs.images)
        if (!resolve_camera(camera, spec()) || img.rgb.size() != std::size_t(img.height) * std::size_t(img.width) * 3 ||
            img.rgb.empty())
          __builtin_trap();
    }
  } catch (const HttpError& e) {
    if (e.status() != 400 || !known_code(e.code()) || std::strlen(e.what()) == 0) __builtin_trap();
  }
  return 0;
}
