// A linear layer's weight prepared once for repeated y = x W^T + b: reordered by oneDNN into the blocked layout
// its matmul kernels read fastest, in float32 or bfloat16. Compute primitives are created once per row count,
// so the steady state (the denoise loop) builds nothing and allocates nothing of its own.
#pragma once

#include <cstdint>
#include <memory>

namespace tether::cpu {

enum class Precision { fp32, bf16 };
const char* precision_name(Precision p);

class PackedLinear {
 public:
  PackedLinear();
  ~PackedLinear();
  PackedLinear(PackedLinear&&) noexcept;
  PackedLinear& operator=(PackedLinear&&) noexcept;

  // weight: [n, k] row-major (nn.Linear); bias: [n] or null. The inputs are copied; callers may free them.
  // bf16 rounds the weights to nearest even and runs the GEMM with bf16 inputs and float32 accumulation.
  void pack(const float* weight, int64_t n, int64_t k, const float* bias, Precision precision);

  // y[m, n] = x[m, k] W^T + b, or with accumulate y += x W^T + b. x is float32 [m, k]; y is float32 with row
  // stride ldy (0: n), so a result can land in the first columns of a wider buffer.
  // Not thread-safe: one caller at a time (each model instance runs one forward pass at a time).
  void forward(const float* x, int64_t m, float* y, bool accumulate = false, int64_t ldy = 0) const;

  int64_t n() const;
  int64_t k() const;
  bool empty() const { return impl_ == nullptr; }

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace tether::cpu
