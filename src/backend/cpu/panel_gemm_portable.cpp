// The panel GEMM in plain C++ (fixed-size arrays the compiler vectorises: NEON on aarch64), 4 rows x 16 columns.
// It is the aarch64 kernel and, on x86, the reference the intrinsic kernels are tested against bit for bit.
#include <cmath>
#include <cstring>

#include "backend/cpu/panel_gemm_impl.h"
#include "core/dtype.h"

namespace tether::cpu::detail {
namespace {

struct Portable {
  static constexpr int width = 8, rows = 4;
  struct reg {
    float v[width];
  };
  static reg zero() { return reg{}; }
  static reg load(const float* p) {
    reg r;
    std::memcpy(r.v, p, sizeof r.v);
    return r;
  }
  static void store(float* p, const reg& r) { std::memcpy(p, r.v, sizeof r.v); }
  static reg broadcast(float s) {
    reg r;
    for (float& v : r.v) v = s;
    return r;
  }
  static reg fma(const reg& a, const reg& b, const reg& c) {
    reg r;
    for (int i = 0; i < width; ++i) r.v[i] = std::fma(a.v[i], b.v[i], c.v[i]);  // one rounding, as the FMA units
    return r;
  }
  static reg add(const reg& a, const reg& b) {
    reg r;
    for (int i = 0; i < width; ++i) r.v[i] = a.v[i] + b.v[i];
    return r;
  }
  static void widen_row(const float* p, reg& lo, reg& hi) {
    lo = load(p);
    hi = load(p + width);
  }
  static void widen_row(const uint16_t* p, reg& lo, reg& hi) {  // paired: word j holds columns j and j + width
    for (int i = 0; i < width; ++i) {
      lo.v[i] = bf16_to_f32(p[2 * i]);
      hi.v[i] = bf16_to_f32(p[2 * i + 1]);
    }
  }
  static void widen_row(const F16* p, reg& lo, reg& hi) {
    for (int i = 0; i < width; ++i) {
      lo.v[i] = f16_to_f32(p[i].bits);
      hi.v[i] = f16_to_f32(p[width + i].bits);
    }
  }
  static void transpose_block(const float* const* src, int n, int64_t k, float* dst) {
    for (int c = 0; c < width; ++c)
      for (int r = 0; r < rows; ++r) dst[c * rows + r] = r < n ? src[r][k + c] : 0.f;
  }
};

using Gemm = PanelGemm<Portable>;
const PanelKernel kKernel{"portable", Gemm::NR, &Gemm::run_f32, &Gemm::run_bf16, &Gemm::run_f16};

}  // namespace

const PanelKernel* panel_kernel_portable() { return &kKernel; }

}  // namespace tether::cpu::detail
