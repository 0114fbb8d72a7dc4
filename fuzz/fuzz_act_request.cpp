// libFuzzer target: any byte string as a POST /act body yields an ActRequest or an HttpError(400) with a contract
// code, nothing else (no crash, no other exception, no observation the engine would reject).
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "fuzz_spec.h"
#include "serve/act_request.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace tether;
  try {
    fuzz::check_accepted(
        serve::parse_act_request(std::string_view(reinterpret_cast<const char*>(data), size), fuzz::fake_spec()));
  } catch (const serve::HttpError& e) {
    fuzz::check_refusal(e, {"bad_json", "invalid_field", "invalid_state", "invalid_image", "unknown_camera",
                            "unknown_field", "missing_field"});
  }
  return 0;
}
