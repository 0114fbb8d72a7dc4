// Shared helpers for the vision tests: fixture paths, file reading, bitwise float comparison.
#pragma once

#include <cmath>
#include <cstdint>
#include <cstring>
#include <fstream>
#include <string>
#include <vector>

#include "core/error.h"
#include "core/json_util.h"
#include "core/safetensors.h"

namespace tether::vision::test {

inline std::string fixture(const std::string& rel) {
  return std::string(TETHER_FIXTURES_DIR) + "/vision/" + rel;
}

inline std::vector<uint8_t> read_bytes(const std::string& path) {
  std::ifstream f(path, std::ios::binary);
  return std::vector<uint8_t>((std::istreambuf_iterator<char>(f)),
                              std::istreambuf_iterator<char>());
}

// A float32 tensor's values in an aligned buffer. Views into a safetensors file need not be 4-byte
// aligned (a file mixing uint8 and float32 tensors can place a float tensor at an odd offset), so
// the bytes are copied rather than read through a float pointer.
inline std::vector<float> f32_values(const Tensor& t) {
  if (t.dtype != DType::f32)
    throw Error(ErrorCode::invalid_argument, "fixture tensor is not float32");
  std::vector<float> v(std::size_t(t.numel()));
  std::memcpy(v.data(), t.data, v.size() * sizeof(float));
  return v;
}

struct Diff {
  double max_abs = 0;
  int64_t mismatched = 0;  // elements whose bits differ
};

inline Diff compare(const float* got, const float* want, int64_t n) {
  Diff d;
  for (int64_t i = 0; i < n; ++i) {
    if (std::memcmp(&got[i], &want[i], sizeof(float)) != 0) ++d.mismatched;
    d.max_abs = std::max(d.max_abs, double(std::fabs(got[i] - want[i])));
  }
  return d;
}

// The generator stores all its metadata as one JSON object under the key "fixture".
inline Json metadata_json(const SafeTensorsFile& f, const std::string& key) {
  return Json::parse(f.metadata().at("fixture")).at(key);
}

}  // namespace tether::vision::test
