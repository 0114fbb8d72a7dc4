#include "core/tensor.h"

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

std::vector<float> Tensor::to_f32() const {
  const int64_t n = numel();
  std::vector<float> out(n);
  auto convert = [&](auto load) {
    for (int64_t i = 0; i < n; ++i) out[i] = load(i);
  };
  switch (dtype) {
    case DType::f32: convert([&](int64_t i) { return as<float>()[i]; }); break;
    case DType::f64: convert([&](int64_t i) { return float(as<double>()[i]); }); break;
    case DType::bf16: convert([&](int64_t i) { return bf16_to_f32(as<uint16_t>()[i]); }); break;
    case DType::f16: convert([&](int64_t i) { return f16_to_f32(as<uint16_t>()[i]); }); break;
    case DType::i64: convert([&](int64_t i) { return float(as<int64_t>()[i]); }); break;
    case DType::i32: convert([&](int64_t i) { return float(as<int32_t>()[i]); }); break;
    case DType::i16: convert([&](int64_t i) { return float(as<int16_t>()[i]); }); break;
    case DType::i8: convert([&](int64_t i) { return float(as<int8_t>()[i]); }); break;
    case DType::u8:
    case DType::boolean: convert([&](int64_t i) { return float(as<uint8_t>()[i]); }); break;
  }
  return out;
}

const float* Tensor::f32_data(std::vector<float>& scratch) const {
  if (dtype == DType::f32) return as<float>();
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
