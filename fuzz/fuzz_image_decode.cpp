// libFuzzer target: image decoding must turn any byte string into an image within the pixel limit or a
// tether::Error, nothing else.
#include <cstddef>
#include <cstdint>

#include "core/error.h"
#include "vision/image.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  try {
    tether::vision::Image img = tether::vision::decode_image(data, size, "fuzz");
    if (img.height < 1 || img.width < 1 || int64_t(img.height) * img.width > tether::vision::kMaxImagePixels)
      __builtin_trap();
    if (img.rgb.size() != std::size_t(img.height) * std::size_t(img.width) * 3) __builtin_trap();
  } catch (const tether::Error&) {
  }
  return 0;
}
