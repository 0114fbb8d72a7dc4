// Dtype names, sizes and the scalar conversions between float formats (see dtype.h).
#include "core/dtype.h"

namespace tether {

namespace {
struct DTypeInfo {
  DType type;
  std::string_view name;
  std::size_t size;
};
constexpr DTypeInfo kTypes[] = {
    {DType::f32, "F32", 4}, {DType::f16, "F16", 2}, {DType::bf16, "BF16", 2},
    {DType::f64, "F64", 8}, {DType::i64, "I64", 8}, {DType::i32, "I32", 4},
    {DType::i16, "I16", 2}, {DType::i8, "I8", 1},   {DType::u8, "U8", 1},
    {DType::boolean, "BOOL", 1},
};
}  // namespace

std::size_t dtype_size(DType t) {
  for (const auto& info : kTypes)
    if (info.type == t) return info.size;
  return 0;
}

std::string_view dtype_name(DType t) {
  for (const auto& info : kTypes)
    if (info.type == t) return info.name;
  return "?";
}

bool dtype_from_name(std::string_view name, DType* out) {
  for (const auto& info : kTypes) {
    if (info.name == name) {
      *out = info.type;
      return true;
    }
  }
  return false;
}

}  // namespace tether
