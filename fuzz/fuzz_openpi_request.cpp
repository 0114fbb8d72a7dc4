// libFuzzer target: any byte string as an openpi observation frame, decoded through the auto layout or a mapping
// file's (chosen by the first byte), yields an ActRequest the engine accepts or an HttpError(400) with one of the
// documented codes; nothing else (no crash, no other exception).
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <string_view>

#include "serve/openpi_protocol.h"

namespace {

using namespace tether;

const models::ModelSpec& spec() {
  static const models::ModelSpec s = [] {
    models::ModelSpec m;
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

const serve::openpi::Layouts& layouts(bool from_file) {
  static const serve::openpi::Layouts automatic = serve::openpi::load_layouts("auto");
  static const serve::openpi::Layouts file = [] {
    serve::openpi::Layouts l;
    l.name = "fuzz.json";
    l.candidates.push_back(serve::openpi::parse_layout_json(
        R"({"images": {"cam/a": "front", "cam/b": "wrist"}, "state": ["s1", "s2"], "prompt": "task",
            "default_prompt": "go", "ignore": ["x"]})",
        "fuzz.json"));
    return l;
  }();
  return from_file ? file : automatic;
}

bool known_code(const std::string& c) {
  for (const char* k : {"invalid_msgpack", "invalid_field", "invalid_image", "invalid_state", "unknown_field",
                        "unknown_camera", "missing_field"})
    if (c == k) return true;
  return false;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size == 0) return 0;
  const bool from_file = data[0] & 1;
  const std::string_view frame(reinterpret_cast<const char*>(data + 1), size - 1);
  try {
    const auto req = serve::openpi::decode_request(frame, layouts(from_file), spec());
    const auto& obs = req.observation;
    if (int64_t(obs.state.size()) != spec().state_dim || obs.images.empty()) __builtin_trap();
    for (const auto& [camera, img] : obs.images) {
      if (!models::find_camera(spec(), camera)) __builtin_trap();
      if (img.rgb.size() != std::size_t(img.height) * std::size_t(img.width) * 3 || img.rgb.empty()) __builtin_trap();
    }
  } catch (const serve::HttpError& e) {
    if (e.status() != 400 || !known_code(e.code()) || std::strlen(e.what()) == 0) __builtin_trap();
  }
  return 0;
}
