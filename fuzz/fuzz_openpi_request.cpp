// libFuzzer target: any byte string as an openpi observation frame, decoded through the auto layout or a mapping
// file's (chosen by the first byte), yields an ActRequest the engine accepts or an HttpError(400) with one of the
// documented codes; nothing else (no crash, no other exception).
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "fuzz_spec.h"
#include "serve/openpi_protocol.h"

namespace {

using namespace tether;

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

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size == 0) return 0;
  const bool from_file = data[0] & 1;
  const std::string_view frame(reinterpret_cast<const char*>(data + 1), size - 1);
  try {
    fuzz::check_accepted(serve::openpi::decode_request(frame, layouts(from_file), fuzz::fake_spec()));
  } catch (const serve::HttpError& e) {
    fuzz::check_refusal(e, {"invalid_msgpack", "invalid_field", "invalid_image", "invalid_state", "unknown_field",
                            "unknown_camera", "missing_field"});
  }
  return 0;
}
