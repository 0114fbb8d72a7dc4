// libFuzzer target: any byte string as a .npy file yields an array whose shape matches its bytes, or an ArrayError;
// nothing is ever unpickled and nothing else is thrown.
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "serve/ndarray.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  using namespace tether::serve;
  try {
    const NdArray a = parse_npy(std::string_view(reinterpret_cast<const char*>(data), size));
    if (a.data.size() != std::size_t(a.elements()) * dtype_size(a.dtype)) __builtin_trap();
    if (a.elements() <= 4096) {
      const auto values = to_float32(a);
      if (int64_t(values.size()) != a.elements()) __builtin_trap();
    }
  } catch (const ArrayError&) {
  }
  return 0;
}
