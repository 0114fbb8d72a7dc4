// libFuzzer target: the safetensors header parser must reject, never crash on, arbitrary bytes.
#include <cstddef>
#include <cstdint>

#include "core/error.h"
#include "core/safetensors.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  try {
    tether::SafeTensorsHeader h = tether::parse_safetensors_header(data, size, "fuzz");
    // Every accepted entry must lie inside the buffer.
    for (const auto& [name, e] : h.tensors)
      if (h.data_offset + e.end > size) __builtin_trap();
  } catch (const tether::Error&) {
  }
  return 0;
}
