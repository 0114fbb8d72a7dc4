// Checked access to a checkpoint's tensors: every weight is verified for name, shape and dtype before use.
// float32 tensors are used in place from the mmap; bf16/f16 (and misaligned f32) tensors are copied to float32
// once at load time.
#pragma once

#include <deque>
#include <string>
#include <vector>

#include "core/safetensors.h"

namespace tether::models {

class Weights {
 public:
  explicit Weights(SafeTensorsFile file) : file_(std::move(file)) {}

  const std::string& path() const { return file_.path(); }
  bool contains(const std::string& name) const { return file_.contains(name); }

  // Float32 view of tensor `name`, which must have exactly `shape`; errors name the file and tensor.
  const float* f32(const std::string& name, const Shape& shape);
  // Like f32() but returns null when the tensor is absent (for optional biases).
  const float* f32_optional(const std::string& name, const Shape& shape);

  // Dtype of the checkpoint's floating-point weights ("F32", "BF16", ...) as found at load time.
  std::string stored_dtype() const { return stored_dtype_; }

 private:
  SafeTensorsFile file_;
  std::deque<std::vector<float>> widened_;  // owned float32 copies of bf16/f16 tensors
  std::string stored_dtype_;
};

}  // namespace tether::models
