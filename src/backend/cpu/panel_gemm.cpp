// Picks the panel GEMM kernel for this CPU, under the TETHER_MAX_CPU_ISA cap.
#include "backend/cpu/panel_gemm.h"

#include <algorithm>
#include <vector>

#include "core/dtype.h"

namespace tether::cpu::detail {

namespace {

// `column_slot(j)` is where column j of a panel row goes (the identity, or the bf16 pairing).
template <class T, class Convert, class Slot>
PanelBuffer<T> pack_panels(const float* w, int64_t n, int64_t k, int nr, Convert convert, Slot column_slot) {
  const int64_t num_panels = (n + nr - 1) / nr;
  PanelBuffer<T> out(std::size_t(num_panels * nr * k), T{});
  for (int64_t row = 0; row < n; ++row) {
    T* dst = out.data() + (row / nr) * k * nr + column_slot(int(row % nr));
    const float* src = w + row * k;
    for (int64_t i = 0; i < k; ++i) dst[i * nr] = convert(src[i]);
  }
  return out;
}

int same_slot(int j) { return j; }

}  // namespace

PanelBuffer<float> pack_f32_panels(const float* w, int64_t n, int64_t k, int nr) {
  return pack_panels<float>(w, n, k, nr, [](float v) { return v; }, same_slot);
}

PanelBuffer<uint16_t> pack_half_panels(const float* w, int64_t n, int64_t k, int nr, PanelType type) {
  if (type == PanelType::bf16) {
    const int half = nr / 2;
    auto paired = [half](int j) { return j < half ? 2 * j : 2 * (j - half) + 1; };
    return pack_panels<uint16_t>(w, n, k, nr, [](float v) { return f32_to_bf16(v); }, paired);
  }
  return pack_panels<uint16_t>(w, n, k, nr, [](float v) { return f32_to_f16(v); }, same_slot);
}

std::vector<float> pad_bias(const float* bias, int64_t n, int nr) {
  std::vector<float> out(std::size_t((n + nr - 1) / nr * nr), 0.0f);
  if (bias) std::copy(bias, bias + n, out.begin());
  return out;
}

int64_t packed_b_floats(int64_t n, int64_t k) {
  const int64_t nr = panel_kernel().panel_width;
  return (n + nr - 1) / nr * nr * k;
}

void pack_b_panels(int64_t n, int64_t k, const float* b, int64_t ldb, bool trans_b, float* panels) {
  const int64_t nr = panel_kernel().panel_width, num_panels = (n + nr - 1) / nr;
  for (int64_t p = 0; p < num_panels; ++p) {
    float* dst = panels + p * k * nr;
    const int64_t cols = std::min(nr, n - p * nr);
    for (int64_t q = 0; q < k; ++q) {
      float* row = dst + q * nr;
      if (trans_b) {
        for (int64_t j = 0; j < cols; ++j) row[j] = b[(p * nr + j) * ldb + q];
      } else {
        std::copy(b + q * ldb + p * nr, b + q * ldb + p * nr + cols, row);
      }
      std::fill(row + cols, row + nr, 0.0f);
    }
  }
}

namespace {
// Zeros for the products without a bias: the kernel always adds one, padded to whole panels.
const float* zero_bias(int64_t n, int64_t nr) {
  thread_local std::vector<float> zeros;
  const std::size_t need = std::size_t((n + nr - 1) / nr * nr);
  if (zeros.size() < need) zeros.assign(need, 0.0f);
  return zeros.data();
}
}  // namespace

void gemm_packed_b(int64_t m, int64_t n, int64_t k, const float* a, int64_t lda, const float* panels, float* c,
                   int64_t ldc) {
  if (m <= 0 || n <= 0) return;
  const PanelKernel& kernel = panel_kernel();
  kernel.f32({a, m, k, lda, panels, n, zero_bias(n, kernel.panel_width), c, ldc, false});
}

void gemm_fixed_order(int64_t m, int64_t n, int64_t k, const float* a, int64_t lda, const float* b, int64_t ldb,
                      bool trans_b, float* c, int64_t ldc, const float* bias) {
  if (m <= 0 || n <= 0) return;
  const PanelKernel& kernel = panel_kernel();
  const int64_t nr = kernel.panel_width;
  thread_local std::vector<float> panels, padded_bias;
  if (panels.size() < std::size_t(packed_b_floats(n, k))) panels.resize(std::size_t(packed_b_floats(n, k)));
  pack_b_panels(n, k, b, ldb, trans_b, panels.data());
  if (!bias) return kernel.f32({a, m, k, lda, panels.data(), n, zero_bias(n, nr), c, ldc, false});
  padded_bias.assign(std::size_t((n + nr - 1) / nr * nr), 0.0f);  // within its capacity after the first call
  std::copy(bias, bias + n, padded_bias.begin());
  kernel.f32({a, m, k, lda, panels.data(), n, padded_bias.data(), c, ldc, false});
}

std::vector<const PanelKernel*> panel_kernels() {
  std::vector<const PanelKernel*> out;
  const CpuIsa isa = cpu_paths().effective;
  if (isa >= CpuIsa::avx512 && panel_kernel_avx512()) out.push_back(panel_kernel_avx512());
  if (isa >= CpuIsa::avx2 && panel_kernel_avx2()) out.push_back(panel_kernel_avx2());
  out.push_back(panel_kernel_portable());
  return out;
}

const PanelKernel& panel_kernel() {
  static const PanelKernel* const kernel = panel_kernels().front();
  return *kernel;
}

}  // namespace tether::cpu::detail
