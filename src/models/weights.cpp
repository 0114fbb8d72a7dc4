#include "models/weights.h"

#include "core/error.h"

namespace tether::models {

const float* Weights::f32(const std::string& name, const Shape& shape) {
  const TensorEntry& e = file_.entry(name);
  if (e.shape != shape)
    throw Error(ErrorCode::format, file_.path() + ": tensor '" + name + "' has shape " + shape_str(e.shape) +
                                       ", the config implies " + shape_str(shape));
  Tensor t = file_.get(name);
  if (stored_dtype_.empty()) stored_dtype_ = std::string(dtype_name(t.dtype));
  switch (t.dtype) {
    case DType::f32:
      if (t.aligned()) return t.as<float>();  // in place from the mmap
      [[fallthrough]];
    case DType::bf16:
    case DType::f16: widened_.push_back(t.to_f32()); return widened_.back().data();
    default:
      throw Error(ErrorCode::unsupported, file_.path() + ": tensor '" + name + "' has dtype " +
                                              std::string(dtype_name(t.dtype)) + ", expected F32, BF16 or F16");
  }
}

const float* Weights::f32_optional(const std::string& name, const Shape& shape) {
  return contains(name) ? f32(name, shape) : nullptr;
}

}  // namespace tether::models
