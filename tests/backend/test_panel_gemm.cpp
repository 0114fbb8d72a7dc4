// The panel GEMM: every kernel this CPU runs against a double-precision reference, bit-identical to each other, and
// batch-invariant (a row's result does not depend on the rows computed with it), at edge and model shapes.
#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <random>
#include <vector>

#include "backend/cpu/panel_gemm.h"
#include "core/dtype.h"

using namespace tether;
using namespace tether::cpu::detail;
using tether::cpu::PanelBuffer;

namespace {

struct Case {
  int64_t m, n, k;
};

// Edge shapes (rows and columns not multiples of any tile, K across block boundaries, rows across the row blocks of
// every kernel) and SmolVLA/pi0 shapes.
const Case kCases[] = {{1, 1, 1},     {5, 17, 3},      {7, 33, 255},  {13, 31, 257},   {50, 720, 720},
                       {50, 32, 720}, {241, 320, 960}, {3, 130, 600}, {129, 48, 513}, {409, 40, 300}};

std::vector<float> random_vec(std::size_t n, std::mt19937& g) {
  std::normal_distribution<float> d(0.f, 1.f);
  std::vector<float> v(n);
  for (auto& x : v) x = d(g);
  return v;
}

struct Packed {
  PanelBuffer<float> f32;
  PanelBuffer<uint16_t> half;
  std::vector<float> bias;
  const void* data(PanelType t) const { return t == PanelType::f32 ? static_cast<const void*>(f32.data()) : half.data(); }
};

Packed pack(const std::vector<float>& w, const std::vector<float>& b, int64_t n, int64_t k, int nr, PanelType t) {
  Packed p;
  if (t == PanelType::f32) p.f32 = pack_f32_panels(w.data(), n, k, nr);
  else p.half = pack_half_panels(w.data(), n, k, nr, t);
  p.bias = pad_bias(b.data(), n, nr);
  return p;
}

std::vector<float> run(const PanelKernel& kernel, PanelType t, const std::vector<float>& x, const std::vector<float>& w,
                       const std::vector<float>& b, const std::vector<float>& y0, Case c, bool accumulate) {
  const Packed p = pack(w, b, c.n, c.k, kernel.panel_width, t);
  std::vector<float> y = accumulate ? y0 : std::vector<float>(std::size_t(c.m * c.n), 99.f);
  kernel.get(t)({x.data(), c.m, c.k, c.k, p.data(t), c.n, p.bias.data(), y.data(), c.n, accumulate});
  return y;
}

float rounded(float v, PanelType t) {
  if (t == PanelType::bf16) return bf16_to_f32(f32_to_bf16(v));
  if (t == PanelType::f16) return f16_to_f32(f32_to_f16(v));
  return v;
}

const char* type_name(PanelType t) { return t == PanelType::bf16 ? "bf16" : t == PanelType::f16 ? "f16" : "f32"; }

}  // namespace

TEST(PanelGemm, EveryKernelMatchesTheReferenceAndEachOther) {
  std::mt19937 g(11);
  const auto kernels = panel_kernels();
  ASSERT_FALSE(kernels.empty());
  for (const Case c : kCases)
    for (PanelType t : {PanelType::f32, PanelType::bf16, PanelType::f16})
      for (bool accumulate : {false, true}) {
        const auto x = random_vec(std::size_t(c.m * c.k), g), w = random_vec(std::size_t(c.n * c.k), g);
        const auto b = random_vec(std::size_t(c.n), g), y0 = random_vec(std::size_t(c.m * c.n), g);
        std::vector<float> first;
        for (const PanelKernel* kernel : kernels) {
          const auto y = run(*kernel, t, x, w, b, y0, c, accumulate);
          double diff = 0;
          for (int64_t i = 0; i < c.m; ++i)
            for (int64_t j = 0; j < c.n; ++j) {
              double want = double(b[j]) + (accumulate ? double(y0[i * c.n + j]) : 0.0);
              for (int64_t q = 0; q < c.k; ++q) want += double(x[i * c.k + q]) * double(rounded(w[j * c.k + q], t));
              diff = std::max(diff, std::fabs(want - double(y[i * c.n + j])));
            }
          EXPECT_LT(diff, 2e-6 * std::sqrt(double(c.k)) * 8) << kernel->name << " " << type_name(t) << " m=" << c.m
                                                              << " n=" << c.n << " k=" << c.k << " acc=" << accumulate;
          if (first.empty()) first = y;
          else
            EXPECT_EQ(0, std::memcmp(first.data(), y.data(), y.size() * sizeof(float)))
                << kernel->name << " differs in bits from " << kernels.front()->name << " (" << type_name(t)
                << " m=" << c.m << " n=" << c.n << " k=" << c.k << ")";
        }
      }
}

TEST(PanelGemm, XWithARowStrideIsPackedExactlyAtEveryTileHeight) {
  // x is packed into row tiles a register block of k steps at a time (a transpose) with a scalar tail: every tile
  // height from 1 row up, k around the block width, and rows a stride apart (attention's heads) must give each
  // kernel the portable kernel's bits and the reference's values.
  std::mt19937 g(23);
  const auto kernels = panel_kernels();
  for (int64_t m = 1; m <= 30; ++m)
    for (int64_t k : {1, 7, 8, 9, 15, 16, 17, 33, 64}) {
      const int64_t n = 40, lda = k + 5;
      const auto x = random_vec(std::size_t(m * lda), g), w = random_vec(std::size_t(n * k), g);
      const auto b = random_vec(std::size_t(n), g);
      std::vector<float> first;
      for (const PanelKernel* kernel : kernels) {
        const Packed p = pack(w, b, n, k, kernel->panel_width, PanelType::f32);
        std::vector<float> y(std::size_t(m * n), 99.f);
        kernel->get(PanelType::f32)({x.data(), m, k, lda, p.data(PanelType::f32), n, p.bias.data(), y.data(), n, false});
        double diff = 0;
        for (int64_t i = 0; i < m; ++i)
          for (int64_t j = 0; j < n; ++j) {
            double want = b[std::size_t(j)];
            for (int64_t q = 0; q < k; ++q) want += double(x[std::size_t(i * lda + q)]) * double(w[std::size_t(j * k + q)]);
            diff = std::max(diff, std::fabs(want - double(y[std::size_t(i * n + j)])));
          }
        EXPECT_LT(diff, 1e-4) << kernel->name << " m=" << m << " k=" << k;
        if (first.empty()) first = y;
        else
          EXPECT_EQ(0, std::memcmp(first.data(), y.data(), y.size() * sizeof(float))) << kernel->name << " m=" << m
                                                                                       << " k=" << k;
      }
    }
}

TEST(PanelGemm, ARowsResultDoesNotDependOnItsBatch) {
  // The server stacks concurrent requests' rows into one GEMM: each row must come out bit for bit as when alone.
  std::mt19937 g(5);
  const Case c{400, 200, 700};  // more rows than one row block of any kernel
  const auto x = random_vec(std::size_t(c.m * c.k), g), w = random_vec(std::size_t(c.n * c.k), g);
  const auto b = random_vec(std::size_t(c.n), g);
  for (const PanelKernel* kernel : panel_kernels())
    for (PanelType t : {PanelType::f32, PanelType::bf16, PanelType::f16}) {
      const auto all = run(*kernel, t, x, w, b, {}, c, false);
      for (int64_t rows : {1, 2, 7, 50}) {
        const Case part{rows, c.n, c.k};
        for (int64_t start : {int64_t(0), int64_t(3), c.m - rows}) {
          const std::vector<float> xs(x.begin() + start * c.k, x.begin() + (start + rows) * c.k);
          const auto y = run(*kernel, t, xs, w, b, {}, part, false);
          EXPECT_EQ(0, std::memcmp(y.data(), all.data() + start * c.n, y.size() * sizeof(float)))
              << kernel->name << " " << type_name(t) << ": rows " << start << ".." << start + rows;
        }
      }
    }
}

TEST(PanelGemm, APackedBGivesGemmFixedOrdersBits) {
  // Attention packs each K and V head once and multiplies every block of queries by the panels: the result must be
  // the one-call product's, bit for bit, with B transposed or not, at edge and attention shapes.
  std::mt19937 g(9);
  for (const Case c : {Case{1, 1, 1}, Case{5, 17, 3}, Case{13, 31, 257}, Case{128, 1024, 64}, Case{50, 256, 320},
                       Case{7, 72, 256}}) {
    for (bool trans_b : {false, true}) {
      const int64_t ldb = (trans_b ? c.k : c.n) + 3;  // a wider row, as K and V heads sit in a row of all heads
      const auto a = random_vec(std::size_t(c.m * c.k), g);
      const auto b = random_vec(std::size_t((trans_b ? c.n : c.k) * ldb), g);
      std::vector<float> want(std::size_t(c.m * c.n)), got(want.size(), 99.f);
      gemm_fixed_order(c.m, c.n, c.k, a.data(), c.k, b.data(), ldb, trans_b, want.data(), c.n);
      std::vector<float> panels(std::size_t(packed_b_floats(c.n, c.k)));
      pack_b_panels(c.n, c.k, b.data(), ldb, trans_b, panels.data());
      gemm_packed_b(c.m, c.n, c.k, a.data(), c.k, panels.data(), got.data(), c.n);
      EXPECT_EQ(0, std::memcmp(got.data(), want.data(), got.size() * sizeof(float)))
          << c.m << "x" << c.n << "x" << c.k << " trans_b=" << trans_b;
    }
  }
}
