// The panel GEMM on AVX-512 (F, BW, VL, DQ; compiled with those flags alone, chosen at run time): 14 rows x 32
// columns per tile.
#if defined(__x86_64__)
#include <immintrin.h>

#include "backend/cpu/panel_gemm_impl.h"

namespace tether::cpu::detail {
namespace {

struct Avx512 {
  using reg = __m512;
  // 28 accumulators + 2 weight vectors + 1 broadcast of 32 registers: 14 rows make 28 FMAs per k step against 16 loads,
  // and amortise the bf16 widening (which shares the FMA ports on Intel cores) over more of them. 14 rows beat 12 by
  // 3-5% on pi0's shapes once x is packed (bench/GEMM.md).
  static constexpr int width = 16, rows = 14;
  static reg zero() { return _mm512_setzero_ps(); }
  static reg load(const float* p) { return _mm512_loadu_ps(p); }
  static void store(float* p, reg v) { _mm512_storeu_ps(p, v); }
  static reg broadcast(float v) { return _mm512_set1_ps(v); }
  static reg fma(reg a, reg b, reg c) { return _mm512_fmadd_ps(a, b, c); }
  static reg add(reg a, reg b) { return _mm512_add_ps(a, b); }
  static void widen_row(const float* p, reg& lo, reg& hi) {
    lo = _mm512_loadu_ps(p);
    hi = _mm512_loadu_ps(p + width);
  }
  // The all-ones maskz forms compute the same as the plain intrinsics; GCC 12 warns that the plain ones' internal
  // _mm512_undefined_*() "may be used uninitialized".
  static constexpr __mmask16 kAll = 0xFFFF;
  // bf16 is the top half of a float32; a paired row holds columns j (low half) and j + 16 (high half) in one word, so
  // one load and two single-uop operations widen 32 columns.
  static void widen_row(const uint16_t* p, reg& lo, reg& hi) {
    const __m512i w = _mm512_loadu_si512(p);
    lo = _mm512_castsi512_ps(_mm512_maskz_slli_epi32(kAll, w, 16));
    hi = _mm512_castsi512_ps(_mm512_maskz_and_epi32(kAll, w, _mm512_set1_epi32(int(0xFFFF0000u))));
  }
  static void widen_row(const F16* p, reg& lo, reg& hi) {
    lo = _mm512_maskz_cvtph_ps(kAll, _mm256_loadu_si256(reinterpret_cast<const __m256i*>(p)));
    hi = _mm512_maskz_cvtph_ps(kAll, _mm256_loadu_si256(reinterpret_cast<const __m256i*>(p + width)));
  }
};

using Gemm = PanelGemm<Avx512>;
const PanelKernel kKernel{"avx512", Gemm::NR, &Gemm::run_f32, &Gemm::run_bf16, &Gemm::run_f16};

}  // namespace

const PanelKernel* panel_kernel_avx512() { return &kKernel; }

}  // namespace tether::cpu::detail
#else
#include "backend/cpu/panel_gemm.h"
namespace tether::cpu::detail {
const PanelKernel* panel_kernel_avx512() { return nullptr; }
}  // namespace tether::cpu::detail
#endif
