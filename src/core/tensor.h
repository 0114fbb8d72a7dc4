// A typed, shaped view of memory. It owns nothing by itself: `owner` keeps the backing storage
// (an mmap'ed file or a heap buffer) alive, so views stay valid after their source is dropped.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "core/dtype.h"

namespace tether {

using Shape = std::vector<int64_t>;

std::string shape_str(const Shape& shape);
int64_t shape_numel(const Shape& shape);

struct Tensor {
  DType dtype = DType::f32;
  Shape shape;
  const void* data = nullptr;
  std::shared_ptr<const void> owner;

  int64_t numel() const { return shape_numel(shape); }
  std::size_t nbytes() const { return std::size_t(numel()) * dtype_size(dtype); }
  int64_t dim(int i) const { return shape.at(i < 0 ? shape.size() + i : i); }

  // Typed pointer; only valid when aligned() (a file may place a tensor at any byte offset).
  template <typename T>
  const T* as() const { return static_cast<const T*>(data); }
  bool aligned() const;

  // Converts any float or integer dtype to float32 (copy).
  std::vector<float> to_f32() const;
  // Converts elements [offset, offset + count) to float32 into `out` (e.g. one row of an embedding table).
  void copy_f32(int64_t offset, int64_t count, float* out) const;
  // Float32 data, zero-copy when already aligned f32; otherwise converted into `scratch`.
  const float* f32_data(std::vector<float>& scratch) const;

  // An owning f32 tensor holding `values`.
  static Tensor from_f32(Shape shape, std::vector<float> values);
};

}  // namespace tether
