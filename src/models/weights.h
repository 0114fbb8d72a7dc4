// Checked access to a checkpoint's tensors: every weight is verified for name, shape and dtype before use.
// float32 tensors are used in place from the mmap; bf16/f16 (and misaligned f32) tensors are copied to float32
// once at load time.
#pragma once

#include <deque>
#include <string>
#include <vector>

#include "backend/cpu/packed_linear.h"
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

  // Several checked tensors converted straight into one float32 buffer, one after another (fused q/k/v or
  // gate/up weights), without an intermediate copy of each.
  std::vector<float> stacked(const std::vector<std::pair<std::string, Shape>>& parts);

  // Checked view in the stored dtype, for tables read a row at a time (token embeddings).
  Tensor raw(const std::string& name, const Shape& shape);

  // After load: the file's pages leave the resident set. Linear weights live in packed copies; the few tensors
  // still read from the mapping (norm weights, embedding rows) fault their pages back in on demand.
  void finish_loading();

  // Dtype of the checkpoint's floating-point weights ("F32", "BF16", ...) as found at load time.
  std::string stored_dtype() const { return stored_dtype_; }

 private:
  const TensorEntry& checked(const std::string& name, const Shape& shape);

  SafeTensorsFile file_;
  std::deque<std::vector<float>> widened_;  // owned float32 copies of bf16/f16 tensors
  std::string stored_dtype_;

};


}  // namespace tether::models
