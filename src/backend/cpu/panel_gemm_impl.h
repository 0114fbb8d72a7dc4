// The panel GEMM's loops and micro-kernel, written once over a small vector abstraction `V` and included by one
// translation unit per ISA (panel_gemm_avx2.cpp, panel_gemm_avx512.cpp, panel_gemm_portable.cpp). V provides:
//   using reg; static constexpr int width, rows (MR);
//   zero(), load(const float*), store(float*, reg), broadcast(float), fma(a, b, c) = a*b + c (one rounding),
//   add(a, b), widen_row(const T* row, reg& lo, reg& hi): one k step of a panel (NR = 2 * width columns) widened to
//   float32, for T = float, bf16 (uint16_t, in the paired layout of pack_half_panels) and f16 (uint16_t, tagged F16),
//   and transpose_block(rows, n, k, dst): dst[c * MR + r] = rows[r][k + c] for c < width, r < n, and 0 for n <= r < MR.
#pragma once

#include <omp.h>

#include <atomic>
#include <cstring>
#include <vector>

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
  // k steps per block: a thread's output tiles are reloaded once per block, so longer blocks mean less of that traffic
  // (a 512-step block of f32 weights, 64 KB, overflows L1 but streams through it in order, which costs less than
  // twice the reloads; measured on the pi0 shapes against 256 and 1024).
  static constexpr int64_t KC = 512;
  // A block of MC rows x KC of packed x stays in L2 (up to 1.3 MB at MR = 14) while every panel of the thread streams
  // past it once: the larger the block, the fewer times the weights are read from memory.
  static constexpr int64_t MC = 32 * MR;
  static int64_t min(int64_t a, int64_t b) { return a < b ? a : b; }
  static int64_t max(int64_t a, int64_t b) { return a < b ? b : a; }

  // Rows are cut into `tiles` tiles of nearly equal height (50 rows: 4 tiles of 12 or 13 at MR = 14, not 3 of 14 and
  // one of 8, whose weight loads would serve 8 rows).
  struct RowTile {
    int64_t first;
    int rows;
  };
  static int64_t row_tiles(int64_t m) { return (m + MR - 1) / MR; }
  static RowTile row_tile(int64_t m, int64_t tiles, int64_t t) {
    const int64_t first = m * t / tiles;
    return {first, int(m * (t + 1) / tiles - first)};
  }

  // x packed per row tile, k-major: tile t's element (r, k) at xp[(t * K + k) * MR + r]. A k step's MR broadcasts then
  // read one or two cache lines instead of MR rows a row stride apart (strides of 4 KB multiples alias in L1), and the
  // hardware prefetcher follows one stream per tile. Unused slots of a short tile are never read.
  // V::width steps at a time are transposed in registers (V::transpose_block): element by element, the packing cost
  // as much as the product itself where N is small (attention's scores times V, N = the head width).
  static void pack_x_tile(const PanelGemmArgs& a, int64_t tiles, int64_t t, float* xp) {
    static_assert(MR <= V::width, "transpose_block writes one register per k step");
    const RowTile tile = row_tile(a.m, tiles, t);
    float* dst = xp + t * a.k * MR;
    const float* rows[MR];
    for (int r = 0; r < tile.rows; ++r) rows[r] = a.x + (tile.first + r) * a.lda;
    int64_t k = 0;
    for (; k + V::width <= a.k; k += V::width) V::transpose_block(rows, tile.rows, k, dst + k * MR);
    for (int r = 0; r < tile.rows; ++r)
      for (int64_t kk = k; kk < a.k; ++kk) dst[kk * MR + r] = rows[r][kk];
  }

  // acc = (first ? (accumulate ? y : 0) : y) + x[rows, k0:k0+kc] W^T; the last block adds the bias.
  // Each element's k loop runs in index order with one rounding per step, whatever `rows` is.
  // `prefetch` (or null): the first `prefetch_rows` k steps of a slice of the panel block the thread reads next,
  // fetched one k step per k step at the start of this tile. Each tile of a row block fetches its own slice, so the
  // next block is in cache when its first tile starts (with 50 rows a block serves only 4 tiles, and the first one
  // would wait on memory) without one tile asking for all of it at once: a 64 KB block requested during one tile
  // exhausts the core's outstanding-miss slots when the weights stream from memory, and stalls that tile.
  // `y_next` (or null): the output tile that follows, whose rows (MR rows a row stride apart, often in L3 by then) are
  // fetched during this tile's first 2 * MR k steps so that its accumulator loads do not wait on them.
  template <class T, int R>
  static void tile(const float* x, const T* panel, int64_t kc, const float* bias, float* y, int64_t ldy, bool load_y,
                   bool last, const T* prefetch, int64_t prefetch_rows, const float* y_next) {
    reg acc[R][2];
    for (int r = 0; r < R; ++r) {
      acc[r][0] = load_y ? V::load(y + r * ldy) : V::zero();
      acc[r][1] = load_y ? V::load(y + r * ldy + V::width) : V::zero();
    }
    const auto step = [&](int64_t k) __attribute__((always_inline)) {
      reg b0, b1;
      V::widen_row(panel + k * NR, b0, b1);
      for (int r = 0; r < R; ++r) {
        const reg a = V::broadcast(x[k * MR + r]);
        acc[r][0] = V::fma(a, b0, acc[r][0]);
        acc[r][1] = V::fma(a, b1, acc[r][1]);
      }
    };
    // The k steps that prefetch, then the rest unrolled with no per-step test (the tests and the loop counter took
    // issue slots from the FMAs: 2-4% on the pi0 shapes with AVX2, bit-identical).
    const int64_t prefetching = y_next ? max(prefetch_rows, 2 * MR) : prefetch_rows;
    const int64_t head = min(kc, prefetching);
    int64_t k = 0;
    for (; k < head; ++k) {
      if (k < prefetch_rows)
        for (std::size_t line = 0; line < NR * sizeof(T); line += 64)
          __builtin_prefetch(reinterpret_cast<const char*>(prefetch + k * NR) + line);
      if (y_next && k < 2 * MR) __builtin_prefetch(y_next + (k >> 1) * ldy + (k & 1) * (NR / 2), 1);
      step(k);
    }
#pragma GCC unroll 4
    for (; k < kc; ++k) step(k);
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
  static void tile_rows(int rows, const float* x, const T* panel, int64_t kc, const float* bias, float* y, int64_t ldy,
                        bool load_y, bool last, const T* prefetch, int64_t prefetch_rows, const float* y_next) {
    if constexpr (R > 0) {
      if (rows == R) return tile<T, R>(x, panel, kc, bias, y, ldy, load_y, last, prefetch, prefetch_rows, y_next);
      return tile_rows<T, R - 1>(rows, x, panel, kc, bias, y, ldy, load_y, last, prefetch, prefetch_rows, y_next);
    }
  }

  // Columns [p0, p1) of the output, as panels, from x packed by pack_x_tile: every k block in order, so each
  // element's chain is the same whichever thread runs the range and however the panels were cut into ranges.
  template <class T>
  static void run_panels(const PanelGemmArgs& a, const float* xp, int64_t p0, int64_t p1) {
    const T* panels = static_cast<const T*>(a.panels);
    alignas(64) float edge[MR * NR];  // the last panel's tile when N is not a multiple of NR
    const int64_t tiles = row_tiles(a.m);
    const int64_t blocks = (tiles * MR + MC - 1) / MC;
    for (int64_t k0 = 0; k0 < a.k; k0 += KC) {
      const int64_t kc = min(KC, a.k - k0);
      const bool first = k0 == 0, last = k0 + kc == a.k;
      const bool load_y = !first || a.accumulate;
      for (int64_t b = 0; b < blocks; ++b) {
        const int64_t t0 = tiles * b / blocks, t1 = tiles * (b + 1) / blocks;
        for (int64_t p = p0; p < p1; ++p) {
          const T* panel = panels + p * a.k * NR + k0 * NR;
          const float* bias = a.bias + p * NR;
          const int64_t cols = min(NR, a.n - p * NR);
          // The next panel's block of the same k range, which the block's tiles fetch a slice each (the range's
          // last panel has no successor here; the next k range starts with a fresh stream).
          const T* next = p + 1 < p1 ? panel + a.k * NR : nullptr;
          for (int64_t t = t0; t < t1; ++t) {
            const RowTile tile = row_tile(a.m, tiles, t);
            const float* x = xp + (t * a.k + k0) * MR;
            float* y = a.y + tile.first * a.ldy + p * NR;
            const int64_t slice0 = kc * (t - t0) / (t1 - t0), slice1 = kc * (t - t0 + 1) / (t1 - t0);
            const T* prefetch = next ? next + slice0 * NR : nullptr;
            const int64_t prefetch_rows = next ? slice1 - slice0 : 0;
            // The output tile after this one, when this block reads y at all: the next row tile, or the block's first
            // one in the next panel.
            const float* y_next = nullptr;
            if (load_y) {
              if (t + 1 < t1) y_next = a.y + row_tile(a.m, tiles, t + 1).first * a.ldy + p * NR;
              else if (p + 1 < p1 && (p + 1) * NR < a.n) y_next = a.y + row_tile(a.m, tiles, t0).first * a.ldy + (p + 1) * NR;
            }
            if (cols == NR) {
              tile_rows<T, MR>(tile.rows, x, panel, kc, bias, y, a.ldy, load_y, last, prefetch, prefetch_rows, y_next);
            } else {
              for (int r = 0; r < tile.rows; ++r) {
                if (load_y) std::memcpy(edge + r * NR, y + r * a.ldy, std::size_t(cols) * sizeof(float));
                std::memset(edge + r * NR + cols, 0, std::size_t(NR - cols) * sizeof(float));
              }
              tile_rows<T, MR>(tile.rows, x, panel, kc, bias, edge, NR, load_y, last, prefetch, prefetch_rows, nullptr);
              for (int r = 0; r < tile.rows; ++r)
                std::memcpy(y + r * a.ldy, edge + r * NR, std::size_t(cols) * sizeof(float));
            }
          }
        }
      }
    }
  }

  // Scratch for packed x, grown once per calling thread and then reused (a nested call, e.g. from attention's
  // parallel heads, runs on its own thread's buffer).
  static float* packed_x_scratch(std::size_t floats) {
    thread_local std::vector<float> scratch;
    if (scratch.size() < floats) scratch.resize(floats);
    return scratch.data();
  }

  template <class T>
  static void run(const PanelGemmArgs& a) {
    if (a.m <= 0 || a.n <= 0) return;
    const int64_t num_panels = (a.n + NR - 1) / NR;
    const int64_t tiles = row_tiles(a.m);
    float* xp = packed_x_scratch(std::size_t(tiles * MR * a.k));
    const int64_t flops = 2 * a.m * a.n * a.k;
    const int threads = flops < (int64_t(1) << 20) ? 1 : int(min(omp_get_max_threads(), num_panels));
    if (threads == 1) {
      for (int64_t t = 0; t < tiles; ++t) pack_x_tile(a, tiles, t, xp);
      return run_panels<T>(a, xp, 0, num_panels);
    }
    // Threads take ranges of panels (columns) from a shared counter, so no two threads touch the same output element
    // and no reduction is ever split: the result does not depend on the thread count. Ranges are handed out as
    // threads become free because a static split leaves the faster thread idle at the end of every GEMM (cores of a
    // shared machine do not run at one speed). x is packed once, by all threads, before any range starts.
    const int64_t range = (num_panels + kRangesPerThread * threads - 1) / (kRangesPerThread * threads);
    std::atomic<int64_t> next_panel{0};
#pragma omp parallel num_threads(threads)
    {
#pragma omp for schedule(static)
      for (int64_t t = 0; t < tiles; ++t) pack_x_tile(a, tiles, t, xp);
      for (;;) {
        const int64_t p0 = next_panel.fetch_add(range, std::memory_order_relaxed);
        if (p0 >= num_panels) break;
        run_panels<T>(a, xp, p0, min(p0 + range, num_panels));
      }
    }
  }
  static constexpr int64_t kRangesPerThread = 4;

  static void run_f32(const PanelGemmArgs& a) { run<float>(a); }
  static void run_bf16(const PanelGemmArgs& a) { run<uint16_t>(a); }
  static void run_f16(const PanelGemmArgs& a) { run<F16>(a); }
};

}  // namespace tether::cpu::detail
