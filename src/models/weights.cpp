#include "models/weights.h"

#include "core/error.h"

namespace tether::models {

const TensorEntry& Weights::checked(const std::string& name, const Shape& shape) {
  const TensorEntry& e = file_.entry(name);
  if (e.shape != shape)
    throw Error(ErrorCode::format, file_.path() + ": tensor '" + name + "' has shape " + shape_str(e.shape) +
                                       ", the config implies " + shape_str(shape));
  if (e.dtype != DType::f32 && e.dtype != DType::bf16 && e.dtype != DType::f16)
    throw Error(ErrorCode::unsupported, file_.path() + ": tensor '" + name + "' has dtype " +
                                            std::string(dtype_name(e.dtype)) + ", expected F32, BF16 or F16");
  if (stored_dtype_.empty()) stored_dtype_ = std::string(dtype_name(e.dtype));
  return e;
}

const float* Weights::f32(const std::string& name, const Shape& shape) {
  checked(name, shape);
  Tensor t = file_.get(name);
  if (t.dtype == DType::f32 && t.aligned()) return t.as<float>();  // in place from the mmap
  widened_.push_back(t.to_f32());
  file_.drop_resident_pages(name);  // copied out: keep peak memory at one copy of the weights
  return widened_.back().data();
}

std::vector<float> Weights::stacked(const std::vector<std::pair<std::string, Shape>>& parts) {
  int64_t total = 0;
  for (const auto& [name, shape] : parts) total += shape_numel(shape);
  std::vector<float> out(static_cast<std::size_t>(total));
  int64_t at = 0;
  for (const auto& [name, shape] : parts) {
    checked(name, shape);
    const Tensor t = file_.get(name);
    t.copy_f32(0, t.numel(), out.data() + at);
    at += t.numel();
    file_.drop_resident_pages(name);  // copied out
  }
  return out;
}

Tensor Weights::raw(const std::string& name, const Shape& shape) {
  checked(name, shape);
  return file_.get(name);  // rows fault in on demand, so it does not pin the file's pages
}

void Weights::finish_loading() { file_.drop_resident_pages(); }

const float* Weights::f32_optional(const std::string& name, const Shape& shape) {
  return contains(name) ? f32(name, shape) : nullptr;
}

}  // namespace tether::models
