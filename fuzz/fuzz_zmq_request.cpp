// libFuzzer target: any byte string as a Tether ZMQ request yields an ActRequest or an HttpError(400) with one of
// /act's codes (or bad_msgpack), nothing else.
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "fuzz_spec.h"
#include "serve/zmq_protocol.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace tether;
  const std::string_view bytes(reinterpret_cast<const char*>(data), size);
  fuzz::check_msgpack_act([&] { return serve::zmqp::decode_message(bytes, fuzz::fake_spec()); });
  return 0;
}
