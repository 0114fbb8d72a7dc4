// The panel GEMM on AVX2 + FMA + F16C (x86-64-v3, the build's baseline): 6 rows x 16 columns per tile.
#if defined(__x86_64__)
#include <immintrin.h>

#include "backend/cpu/panel_gemm_impl.h"

namespace tether::cpu::detail {
namespace {

struct Avx2 {
  using reg = __m256;
  static constexpr int width = 8, rows = 6;  // 12 accumulators + 2 weight vectors + 1 broadcast of 16 registers
  static reg zero() { return _mm256_setzero_ps(); }
  static reg load(const float* p) { return _mm256_loadu_ps(p); }
  static void store(float* p, reg v) { _mm256_storeu_ps(p, v); }
  static reg broadcast(float v) { return _mm256_set1_ps(v); }
  static reg fma(reg a, reg b, reg c) { return _mm256_fmadd_ps(a, b, c); }
  static reg add(reg a, reg b) { return _mm256_add_ps(a, b); }
  static void widen_row(const float* p, reg& lo, reg& hi) {
    lo = _mm256_loadu_ps(p);
    hi = _mm256_loadu_ps(p + width);
  }
  // bf16 is the top half of a float32; a paired row holds columns j (low half) and j + 8 (high half) in one word.
  // The low word moves up by a byte shuffle, not a shift: on Intel cores a vector shift issues only on the two ports
  // that run the k step's 12 FMAs, and the shuffle also on port 5 (bench/GEMM.md, the bf16 widening on AVX2).
  static void widen_row(const uint16_t* p, reg& lo, reg& hi) {
    const __m256i w = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(p));
    const __m256i low_word_up = _mm256_setr_epi8(-1, -1, 0, 1, -1, -1, 4, 5, -1, -1, 8, 9, -1, -1, 12, 13,  //
                                                 -1, -1, 0, 1, -1, -1, 4, 5, -1, -1, 8, 9, -1, -1, 12, 13);
    lo = _mm256_castsi256_ps(_mm256_shuffle_epi8(w, low_word_up));
    hi = _mm256_castsi256_ps(_mm256_and_si256(w, _mm256_set1_epi32(int(0xFFFF0000u))));
  }
  static void widen_row(const F16* p, reg& lo, reg& hi) {
    lo = _mm256_cvtph_ps(_mm_loadu_si128(reinterpret_cast<const __m128i*>(p)));
    hi = _mm256_cvtph_ps(_mm_loadu_si128(reinterpret_cast<const __m128i*>(p + width)));
  }
  // 8 steps of up to 8 rows as an 8 x 8 transpose; each step's `rows` values go out in one masked store.
  static void transpose_block(const float* const* src, int n, int64_t k, float* dst) {
    __m256 r[8], t[8];
    for (int i = 0; i < 8; ++i) r[i] = i < n ? _mm256_loadu_ps(src[i] + k) : _mm256_setzero_ps();
    for (int i = 0; i < 8; i += 2) {
      t[i] = _mm256_unpacklo_ps(r[i], r[i + 1]);
      t[i + 1] = _mm256_unpackhi_ps(r[i], r[i + 1]);
    }
    for (int i = 0; i < 8; i += 4) {  // r[i + j], 128-bit lane L: rows i..i+3 at column 4L + j
      r[i] = _mm256_shuffle_ps(t[i], t[i + 2], _MM_SHUFFLE(1, 0, 1, 0));
      r[i + 1] = _mm256_shuffle_ps(t[i], t[i + 2], _MM_SHUFFLE(3, 2, 3, 2));
      r[i + 2] = _mm256_shuffle_ps(t[i + 1], t[i + 3], _MM_SHUFFLE(1, 0, 1, 0));
      r[i + 3] = _mm256_shuffle_ps(t[i + 1], t[i + 3], _MM_SHUFFLE(3, 2, 3, 2));
    }
    const __m256i mask = _mm256_cmpgt_epi32(_mm256_set1_epi32(rows), _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7));
    for (int j = 0; j < 4; ++j) {
      _mm256_maskstore_ps(dst + j * rows, mask, _mm256_permute2f128_ps(r[j], r[4 + j], 0x20));
      _mm256_maskstore_ps(dst + (4 + j) * rows, mask, _mm256_permute2f128_ps(r[j], r[4 + j], 0x31));
    }
  }
};

using Gemm = PanelGemm<Avx2>;
const PanelKernel kKernel{"avx2", Gemm::NR, &Gemm::run_f32, &Gemm::run_bf16, &Gemm::run_f16};

}  // namespace

const PanelKernel* panel_kernel_avx2() { return &kKernel; }

}  // namespace tether::cpu::detail
#else
#include "backend/cpu/panel_gemm.h"
namespace tether::cpu::detail {
const PanelKernel* panel_kernel_avx2() { return nullptr; }
}  // namespace tether::cpu::detail
#endif
