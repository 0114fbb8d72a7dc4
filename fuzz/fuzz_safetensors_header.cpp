// libFuzzer target: the safetensors header parser must reject, never crash on, arbitrary bytes, and every tensor it
// accepts must be one the rest of the code can size.
#include <cstddef>
#include <cstdint>

#include "core/error.h"
#include "core/safetensors.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  try {
    tether::SafeTensorsHeader h = tether::parse_safetensors_header(data, size, "fuzz");
    // Every accepted entry must lie inside the buffer and describe a tensor the rest of the code can size:
    // non-negative dims whose product, taken left to right as Tensor::numel() takes it, never overflows int64_t
    // (checked here, not left to UBSan, so the gcc replay of the regressions catches it too) and matches the bytes.
    for (const auto& [name, e] : h.tensors) {
      if (h.data_offset + e.end > size) __builtin_trap();
      int64_t numel = 1;
      for (const int64_t d : e.shape)
        if (d < 0 || __builtin_mul_overflow(numel, d, &numel)) __builtin_trap();
      if (numel != tether::shape_numel(e.shape)) __builtin_trap();
      if (uint64_t(numel) * tether::dtype_size(e.dtype) != e.end - e.begin) __builtin_trap();
    }
  } catch (const tether::Error&) {
  }
  return 0;
}
