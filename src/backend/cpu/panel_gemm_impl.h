// The panel GEMM's loops and micro-kernel, written once over a small vector abstraction `V` and included by one
// translation unit per ISA (panel_gemm_avx2.cpp, panel_gemm_avx512.cpp, panel_gemm_portable.cpp). V provides:
//   using reg; static constexpr int width, rows (MR);
//   zero(), load(const float*), store(float*, reg), broadcast(float), fma(a, b, c) = a*b + c (one rounding),
//   add(a, b), and widen_row(const T* row, reg& lo, reg& hi): one k step of a panel (NR = 2 * width columns) widened to
//   float32, for T = float, bf16 (uint16_t, in the paired layout of pack_half_panels) and f16 (uint16_t, tagged F16).
#pragma once

#include <omp.h>

#include <atomic>
#include <cstring>

#include "backend/cpu/panel_gemm.h"

namespace tether::cpu::detail {

struct F16 {  // tag: a uint16_t panel holding IEEE half floats (bf16 is plain uint16_t)
  uint16_t bits;
};

// Every function here is a member of a template instantiated with a TU-local V, so each ISA's translation unit
// keeps its own copies (no std:: inline template is shared with code compiled for a lower ISA).
template <class V>
struct PanelGemm {
  using reg = typename V::reg;
  static constexpr int NR = 2 * V::width;  // two vector registers of columns
  static constexpr int MR = V::rows;
  // A panel block of KC x NR weights stays in L1 (32 KB at NR = 32 in either dtype); half-size weights take twice
  // the k steps per block, which halves how often the output tiles are reloaded (that traffic dominates at K = 16384).
  template <class T>
  static constexpr int64_t KC = sizeof(T) == 2 ? 512 : 256;
  // An MC x KC block of x stays in L2 (384 KB at MR = 12) while every panel of the thread streams past it once: the
  // larger the block, the fewer times the weights are read from memory (the prefix's M of ~300 is one block).
  static constexpr int64_t MC = 32 * MR;
  static int64_t min(int64_t a, int64_t b) { return a < b ? a : b; }

  // acc = (first ? (accumulate ? y : 0) : y) + x[rows, k0:k0+kc] W^T; the last block adds the bias.
  // Each element's k loop runs in index order with one rounding per step, whatever `rows` is.
  // `prefetch` (or null): the panel block the thread reads next, fetched one k step per k step so that it is in cache
  // when its first tile starts (with 50 rows a block serves only 5 tiles, and the first one would wait on memory).
  template <class T, int R>
  static void tile(const float* x, int64_t lda, const T* panel, int64_t kc, const float* bias, float* y,
                   int64_t ldy, bool load_y, bool last, const T* prefetch) {
    reg acc[R][2];
    for (int r = 0; r < R; ++r) {
      acc[r][0] = load_y ? V::load(y + r * ldy) : V::zero();
      acc[r][1] = load_y ? V::load(y + r * ldy + V::width) : V::zero();
    }
    for (int64_t k = 0; k < kc; ++k) {
      if (prefetch)
        for (std::size_t line = 0; line < NR * sizeof(T); line += 64)
          __builtin_prefetch(reinterpret_cast<const char*>(prefetch + k * NR) + line);
      reg b0, b1;
      V::widen_row(panel + k * NR, b0, b1);
      for (int r = 0; r < R; ++r) {
        const reg a = V::broadcast(x[r * lda + k]);
        acc[r][0] = V::fma(a, b0, acc[r][0]);
        acc[r][1] = V::fma(a, b1, acc[r][1]);
      }
    }
    if (last) {
      const reg b0 = V::load(bias), b1 = V::load(bias + V::width);
      for (int r = 0; r < R; ++r) {
        acc[r][0] = V::add(acc[r][0], b0);
        acc[r][1] = V::add(acc[r][1], b1);
      }
    }
    for (int r = 0; r < R; ++r) {
      V::store(y + r * ldy, acc[r][0]);
      V::store(y + r * ldy + V::width, acc[r][1]);
    }
  }

  template <class T, int R>
  static void tile_rows(int rows, const float* x, int64_t lda, const T* panel, int64_t kc, const float* bias,
                        float* y, int64_t ldy, bool load_y, bool last, const T* prefetch) {
    if constexpr (R > 0) {
      if (rows == R) return tile<T, R>(x, lda, panel, kc, bias, y, ldy, load_y, last, prefetch);
      return tile_rows<T, R - 1>(rows, x, lda, panel, kc, bias, y, ldy, load_y, last, prefetch);
    }
  }

  // Columns [p0, p1) of the output, as panels: every k block in order, so each element's chain is the same whichever
  // thread runs the range and however the panels were cut into ranges.
  template <class T>
  static void run_panels(const PanelGemmArgs& a, int64_t p0, int64_t p1) {
    const T* panels = static_cast<const T*>(a.panels);
    alignas(64) float edge[MR * NR];  // the last panel's tile when N is not a multiple of NR
    for (int64_t k0 = 0; k0 < a.k; k0 += KC<T>) {
      const int64_t kc = min(KC<T>, a.k - k0);
      const bool first = k0 == 0, last = k0 + kc == a.k;
      const bool load_y = !first || a.accumulate;
      // Row blocks and the tiles within a block are split evenly (50 rows: 5 tiles of 10 at MR = 12, not 4 of 12
      // and one of 2, whose weight loads would serve 4 FMAs per k step).
      const int64_t blocks = (a.m + MC - 1) / MC;
      for (int64_t b = 0; b < blocks; ++b) {
        const int64_t i0 = a.m * b / blocks, mc = a.m * (b + 1) / blocks - i0;
        const int64_t tiles = (mc + MR - 1) / MR;
        for (int64_t p = p0; p < p1; ++p) {
          const T* panel = panels + p * a.k * NR + k0 * NR;
          const float* bias = a.bias + p * NR;
          const int64_t cols = min(NR, a.n - p * NR);
          // The next panel's block of the same k range, which the first tile fetches (the range's last panel has
          // no successor here; the next k range starts with a fresh stream).
          const T* next = p + 1 < p1 ? panel + a.k * NR : nullptr;
          for (int64_t t_row = 0; t_row < tiles; ++t_row) {
            const int64_t i = i0 + mc * t_row / tiles;
            const int rows = int(i0 + mc * (t_row + 1) / tiles - i);
            const float* x = a.x + i * a.lda + k0;
            float* y = a.y + i * a.ldy + p * NR;
            const T* prefetch = t_row == 0 ? next : nullptr;
            if (cols == NR) {
              tile_rows<T, MR>(rows, x, a.lda, panel, kc, bias, y, a.ldy, load_y, last, prefetch);
            } else {
              for (int r = 0; r < rows; ++r) {
                if (load_y) std::memcpy(edge + r * NR, y + r * a.ldy, std::size_t(cols) * sizeof(float));
                std::memset(edge + r * NR + cols, 0, std::size_t(NR - cols) * sizeof(float));
              }
              tile_rows<T, MR>(rows, x, a.lda, panel, kc, bias, edge, NR, load_y, last, prefetch);
              for (int r = 0; r < rows; ++r)
                std::memcpy(y + r * a.ldy, edge + r * NR, std::size_t(cols) * sizeof(float));
            }
          }
        }
      }
    }
  }

  template <class T>
  static void run(const PanelGemmArgs& a) {
    const int64_t num_panels = (a.n + NR - 1) / NR;
    const int64_t flops = 2 * a.m * a.n * a.k;
    const int threads = flops < (int64_t(1) << 20) ? 1 : int(min(omp_get_max_threads(), num_panels));
    if (threads == 1) return run_panels<T>(a, 0, num_panels);
    // Threads take ranges of panels (columns) from a shared counter, so no two threads touch the same output element
    // and no reduction is ever split: the result does not depend on the thread count. Ranges are handed out as
    // threads become free because a static split leaves the faster thread idle at the end of every GEMM (cores of a
    // shared machine do not run at one speed). Each range re-reads the rows of x, so there are only a few per thread.
    const int64_t range = (num_panels + kRangesPerThread * threads - 1) / (kRangesPerThread * threads);
    std::atomic<int64_t> next_panel{0};
#pragma omp parallel num_threads(threads)
    for (;;) {
      const int64_t p0 = next_panel.fetch_add(range, std::memory_order_relaxed);
      if (p0 >= num_panels) break;
      run_panels<T>(a, p0, min(p0 + range, num_panels));
    }
  }
  static constexpr int64_t kRangesPerThread = 4;

  static void run_f32(const PanelGemmArgs& a) { run<float>(a); }
  static void run_bf16(const PanelGemmArgs& a) { run<uint16_t>(a); }
  static void run_f16(const PanelGemmArgs& a) { run<F16>(a); }
};

}  // namespace tether::cpu::detail
