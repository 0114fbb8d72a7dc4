// A linear layer's weight prepared once for repeated y = x W^T + b. Two paths, chosen per precision and CPU:
// - oneDNN matmul, weights reordered into its blocked layout: float32, and bf16 where the CPU has bf16
//   instructions (bf16 weights and inputs, float32 accumulation). Primitives are created once per row count, so
//   the steady state (the denoise loop) builds nothing and allocates nothing of its own.
// - the panel GEMM (panel_gemm.h): bf16 or fp16 weights widened to float32 inside the kernel, inputs and
//   accumulation in float32, on every CPU. It keeps half-size weights where bf16 is not native, and for fp32 it
//   keeps weights that are all bf16 values (a bf16 checkpoint) as bf16 panels: exact, at half the memory.
#pragma once

#include <cstdint>
#include <memory>
#include <string>

namespace tether::cpu {

enum class Precision { fp32, bf16, fp16 };
const char* precision_name(Precision p);  // "fp32", "bf16", "fp16"
// Parses "fp32" / "bf16" / "fp16"; throws tether::Error naming the value otherwise.
Precision parse_precision(const std::string& name);

enum class LinearPath { onednn_f32, onednn_bf16, panel_f32, panel_bf16, panel_f16 };
// The path `precision` takes on this CPU (under TETHER_MAX_CPU_ISA).
LinearPath linear_path(Precision precision);
// What runs, for inference_mode, bench and doctor: "fp32", "bf16" (native bf16 GEMM), "bf16-weights" or
// "fp16-weights" (half-size weights widened to float32 in the kernel).
const char* compute_mode(Precision precision);
// The GEMM behind `precision` here: "onednn", or "panel-avx512" / "panel-avx2" / "panel-portable".
std::string gemm_name(Precision precision);
// One line on how `precision` runs here, e.g. "bf16 weights widened to fp32 in the kernel (avx2): no native bf16".
std::string compute_mode_description(Precision precision);

class PackedLinear {
 public:
  PackedLinear();
  ~PackedLinear();
  PackedLinear(PackedLinear&&) noexcept;
  PackedLinear& operator=(PackedLinear&&) noexcept;

  // weight: [n, k] row-major (nn.Linear); bias: [n] or null. The inputs are copied; callers may free them.
  // bf16 / fp16 round the weights to nearest even (values already in that dtype are kept exactly).
  void pack(const float* weight, int64_t n, int64_t k, const float* bias, Precision precision);

  // y[m, n] = x[m, k] W^T + b, or with accumulate y += x W^T + b. x is float32 [m, k]; y is float32 with row
  // stride ldy (0: n), so a result can land in the first columns of a wider buffer.
  // Not thread-safe: one caller at a time (each model instance runs one forward pass at a time).
  void forward(const float* x, int64_t m, float* y, bool accumulate = false, int64_t ldy = 0) const;

  LinearPath path() const;
  // The kernel that forward(x, m, y, accumulate, ldy) runs: oneDNN's implementation name (e.g.
  // "brg:avx512_core_amx_bf16"; "ref:any" would be its slow reference kernel) or "panel-avx512" / "panel-avx2" /
  // "panel-portable".
  std::string kernel(int64_t m, bool accumulate = false, int64_t ldy = 0) const;
  int64_t n() const;
  int64_t k() const;
  bool empty() const { return impl_ == nullptr; }

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace tether::cpu
