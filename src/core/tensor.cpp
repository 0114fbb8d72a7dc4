// Tensor views: shapes, alignment and conversion of stored dtypes to float32 (see tensor.h).
#include "core/tensor.h"

#include <cstring>

#include "core/error.h"

namespace tether {

std::string shape_str(const Shape& shape) {
  std::string s = "[";
  for (std::size_t i = 0; i < shape.size(); ++i) {
    if (i) s += ", ";
    s += std::to_string(shape[i]);
  }
  return s + "]";
}

int64_t shape_numel(const Shape& shape) {
  int64_t n = 1;
  for (int64_t d : shape) n *= d;
  return n;
}

namespace {

// Element loads go through memcpy: safetensors writers do not all align tensors to their element size.
template <typename T>
T load(const void* base, int64_t i) {
  T v;
  std::memcpy(&v, static_cast<const char*>(base) + i * int64_t(sizeof(T)), sizeof(T));
  return v;
}

}  // namespace

std::vector<float> Tensor::to_f32() const {
  std::vector<float> out(static_cast<std::size_t>(numel()));
  copy_f32(0, numel(), out.data());
  return out;
}

void Tensor::copy_f32(int64_t offset, int64_t count, float* out) const {
  if (offset < 0 || count < 0 || offset + count > numel())
    throw Error(ErrorCode::internal, "Tensor::copy_f32: range outside a tensor of shape " + shape_str(shape));
  auto convert = [&](auto fn) {
    for (int64_t i = 0; i < count; ++i) out[i] = fn(offset + i);
  };
  switch (dtype) {
    case DType::f32:
      if (count) std::memcpy(out, static_cast<const char*>(data) + offset * 4, std::size_t(count) * 4);
      break;
    case DType::f64: convert([&](int64_t i) { return float(load<double>(data, i)); }); break;
    case DType::bf16: convert([&](int64_t i) { return bf16_to_f32(load<uint16_t>(data, i)); }); break;
    case DType::f16: convert([&](int64_t i) { return f16_to_f32(load<uint16_t>(data, i)); }); break;
    case DType::i64: convert([&](int64_t i) { return float(load<int64_t>(data, i)); }); break;
    case DType::i32: convert([&](int64_t i) { return float(load<int32_t>(data, i)); }); break;
    case DType::i16: convert([&](int64_t i) { return float(load<int16_t>(data, i)); }); break;
    case DType::i8: convert([&](int64_t i) { return float(load<int8_t>(data, i)); }); break;
    case DType::u8:
    case DType::boolean: convert([&](int64_t i) { return float(load<uint8_t>(data, i)); }); break;
  }
}

bool Tensor::aligned() const { return reinterpret_cast<uintptr_t>(data) % dtype_size(dtype) == 0; }

const float* Tensor::f32_data(std::vector<float>& scratch) const {
  if (dtype == DType::f32 && aligned()) return as<float>();
  scratch = to_f32();
  return scratch.data();
}

Tensor Tensor::from_f32(Shape shape, std::vector<float> values) {
  if (shape_numel(shape) != int64_t(values.size()))
    throw Error(ErrorCode::internal, "Tensor::from_f32: shape " + shape_str(shape) + " does not match " +
                                         std::to_string(values.size()) + " values");
  auto storage = std::make_shared<std::vector<float>>(std::move(values));
  Tensor t;
  t.dtype = DType::f32;
  t.shape = std::move(shape);
  t.data = storage->data();
  t.owner = storage;
  return t;
}

}  // namespace tether
