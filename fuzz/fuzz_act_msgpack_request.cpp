// libFuzzer target: any byte string as a POST /act body with Content-Type: application/msgpack yields an ActRequest or
// an HttpError(400) with one of /act's codes (or bad_msgpack), nothing else.
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "fuzz_spec.h"
#include "serve/zmq_protocol.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace tether;
  try {
    const serve::ActRequest req =
        serve::zmqp::decode_http_body(std::string_view(reinterpret_cast<const char*>(data), size), fuzz::fake_spec());
    fuzz::check_accepted(req);
    if (req.rtc && (req.rtc->rows < 1 ||
                    int64_t(req.rtc->prev_actions.size()) != req.rtc->rows * fuzz::fake_spec().action_dim))
      __builtin_trap();
  } catch (const serve::HttpError& e) {
    fuzz::check_refusal(e, {"bad_msgpack", "invalid_field", "invalid_state", "invalid_image", "unknown_camera",
                            "unknown_field", "missing_field"});
  }
  return 0;
}
