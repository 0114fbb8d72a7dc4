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
  static constexpr __mmask8 kAll8 = 0xFF;
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
  // 16 steps of up to 16 rows as a 16 x 16 transpose (32-bit, then 64-bit unpacks, then two 128-bit lane shuffles);
  // each step's `rows` values go out in one masked store.
  static void transpose_block(const float* const* src, int n, int64_t k, float* dst) {
    __m512 r[16], t[16];
    for (int i = 0; i < 16; ++i) r[i] = i < n ? _mm512_loadu_ps(src[i] + k) : _mm512_setzero_ps();
    for (int i = 0; i < 16; i += 2) {  // lane L: rows i, i + 1 at columns 4L..4L+1 (lo) and 4L+2..4L+3 (hi)
      t[i] = _mm512_maskz_unpacklo_ps(kAll, r[i], r[i + 1]);
      t[i + 1] = _mm512_maskz_unpackhi_ps(kAll, r[i], r[i + 1]);
    }
    for (int i = 0; i < 16; i += 4) {  // r[i + j], lane L: rows i..i+3 at column 4L + j
      const __m512d a = _mm512_castps_pd(t[i]), b = _mm512_castps_pd(t[i + 1]);
      const __m512d c = _mm512_castps_pd(t[i + 2]), d = _mm512_castps_pd(t[i + 3]);
      r[i] = _mm512_castpd_ps(_mm512_maskz_unpacklo_pd(kAll8, a, c));
      r[i + 1] = _mm512_castpd_ps(_mm512_maskz_unpackhi_pd(kAll8, a, c));
      r[i + 2] = _mm512_castpd_ps(_mm512_maskz_unpacklo_pd(kAll8, b, d));
      r[i + 3] = _mm512_castpd_ps(_mm512_maskz_unpackhi_pd(kAll8, b, d));
    }
    constexpr __mmask16 kRows = __mmask16((1u << rows) - 1);
    for (int j = 0; j < 4; ++j) {  // columns j, 4 + j, 8 + j, 12 + j: lane L of r[j], r[4 + j], r[8 + j], r[12 + j]
      const __m512 v0 = _mm512_maskz_shuffle_f32x4(kAll, r[j], r[4 + j], 0x88);
      const __m512 v1 = _mm512_maskz_shuffle_f32x4(kAll, r[j], r[4 + j], 0xDD);
      const __m512 v2 = _mm512_maskz_shuffle_f32x4(kAll, r[8 + j], r[12 + j], 0x88);
      const __m512 v3 = _mm512_maskz_shuffle_f32x4(kAll, r[8 + j], r[12 + j], 0xDD);
      _mm512_mask_storeu_ps(dst + (j)*rows, kRows, _mm512_maskz_shuffle_f32x4(kAll, v0, v2, 0x88));
      _mm512_mask_storeu_ps(dst + (4 + j) * rows, kRows, _mm512_maskz_shuffle_f32x4(kAll, v1, v3, 0x88));
      _mm512_mask_storeu_ps(dst + (8 + j) * rows, kRows, _mm512_maskz_shuffle_f32x4(kAll, v0, v2, 0xDD));
      _mm512_mask_storeu_ps(dst + (12 + j) * rows, kRows, _mm512_maskz_shuffle_f32x4(kAll, v1, v3, 0xDD));
    }
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
