// PackedLinear on every precision and whichever path this CPU takes for it (oneDNN, or the panel GEMM with widened
// weights), against a double-precision reference.
#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <vector>

#include "backend/cpu/cpu_features.h"
#include "backend/cpu/packed_linear.h"
#include "backend/cpu/panel_gemm.h"
#include "core/dtype.h"

using namespace tether;
using namespace tether::cpu;

namespace {

std::vector<float> random_vec(std::size_t n, std::mt19937& g) {
  std::normal_distribution<float> d(0.f, 1.f);
  std::vector<float> v(n);
  for (auto& x : v) x = d(g);
  return v;
}

double bf16_round(float v) { return bf16_to_f32(f32_to_bf16(v)); }
double f16_round(float v) { return f16_to_f32(f32_to_f16(v)); }
double exact(float v) { return v; }

// y = x W^T + b (+ y0), in double, with x and W rounded as the path rounds them.
std::vector<double> reference(const std::vector<float>& x, const std::vector<float>& w, const std::vector<float>& b,
                              const std::vector<float>& y0, int64_t m, int64_t n, int64_t k, Precision prec) {
  const LinearPath path = linear_path(prec);
  double (*rx)(float) = path == LinearPath::onednn_bf16 ? bf16_round : exact;  // only native bf16 rounds inputs
  double (*rw)(float) = prec == Precision::bf16 ? bf16_round : prec == Precision::fp16 ? f16_round : exact;
  std::vector<double> y(std::size_t(m * n));
  for (int64_t i = 0; i < m; ++i)
    for (int64_t j = 0; j < n; ++j) {
      double acc = b.empty() ? 0.0 : b[j];
      for (int64_t t = 0; t < k; ++t) acc += rx(x[i * k + t]) * rw(w[j * k + t]);
      y[i * n + j] = acc + (y0.empty() ? 0.0 : y0[i * n + j]);
    }
  return y;
}

}  // namespace

TEST(PackedLinear, MatchesReferenceAcrossShapesAndModes) {
  std::mt19937 g(7);
  struct Shape {
    int64_t m, n, k;
  };
  for (const Shape s : {Shape{1, 7, 5}, Shape{50, 96, 72}, Shape{241, 64, 96}, Shape{3, 130, 33}, Shape{13, 40, 600}}) {
    for (Precision prec : {Precision::fp32, Precision::bf16, Precision::fp16}) {
      for (bool with_bias : {false, true}) {
        for (bool accumulate : {false, true}) {
          const auto x = random_vec(std::size_t(s.m * s.k), g), w = random_vec(std::size_t(s.n * s.k), g);
          const auto b = with_bias ? random_vec(std::size_t(s.n), g) : std::vector<float>{};
          const auto y0 = accumulate ? random_vec(std::size_t(s.m * s.n), g) : std::vector<float>{};
          PackedLinear lin;
          lin.pack(w.data(), s.n, s.k, with_bias ? b.data() : nullptr, prec);
          std::vector<float> y = accumulate ? y0 : std::vector<float>(std::size_t(s.m * s.n), 123.f);
          lin.forward(x.data(), s.m, y.data(), accumulate);
          const auto want = reference(x, w, b, y0, s.m, s.n, s.k, prec);
          double diff = 0;
          for (std::size_t i = 0; i < y.size(); ++i) diff = std::max(diff, std::fabs(double(y[i]) - want[i]));
          // Rounded inputs are exact; only the float32 accumulation order differs from the reference.
          EXPECT_LT(diff, 2e-5 * std::sqrt(double(s.k))) << precision_name(prec) << " (" << compute_mode(prec) << ")" << " m=" << s.m << " n=" << s.n
                                                         << " k=" << s.k << " bias=" << with_bias << " acc=" << accumulate;
        }
      }
    }
  }
}

TEST(PackedLinear, WritesIntoAWiderBuffer) {
  std::mt19937 g(3);
  const int64_t m = 4, n = 6, k = 8, ldy = 10;
  const auto x = random_vec(m * k, g), w = random_vec(n * k, g);
  for (Precision prec : {Precision::fp32, Precision::bf16, Precision::fp16}) {
    PackedLinear lin;
    lin.pack(w.data(), n, k, nullptr, prec);
    std::vector<float> y(std::size_t(m * ldy), -7.f);
    lin.forward(x.data(), m, y.data(), false, ldy);
    const auto want = reference(x, w, {}, {}, m, n, k, prec);
    for (int64_t i = 0; i < m; ++i) {
      for (int64_t j = 0; j < n; ++j) EXPECT_NEAR(y[i * ldy + j], want[i * n + j], 1e-5) << precision_name(prec);
      for (int64_t j = n; j < ldy; ++j) EXPECT_EQ(y[i * ldy + j], -7.f);  // columns past n untouched
    }
  }
}

// oneDNN 2.6 runs a matmul it has no fast kernel for on its reference kernel, 10 to 100 times slower and silently:
// a strided result did (GR00T's action encoder writes into half of a wider buffer), and only AVX-512 and AMX showed
// it. Every model shape kind here, strided or not, must run on a real kernel, with the right result.
TEST(PackedLinear, NoShapeRunsOnOneDnnsReferenceKernel) {
  std::mt19937 g(11);
  struct Shape {
    int64_t m, n, k;
  };
  int checked = 0;
  for (Precision prec : {Precision::fp32, Precision::bf16}) {
    const LinearPath path = linear_path(prec);
    if (path != LinearPath::onednn_f32 && path != LinearPath::onednn_bf16) continue;
    for (const Shape s : {Shape{40, 1536, 132}, Shape{1, 1536, 132}, Shape{41, 132, 1024}, Shape{50, 1024, 32},
                          Shape{3, 130, 33}, Shape{1, 7, 5}}) {
      for (bool accumulate : {false, true}) {
        const int64_t ldy = 2 * s.n;
        const auto x = random_vec(std::size_t(s.m * s.k), g), w = random_vec(std::size_t(s.n * s.k), g);
        const auto b = random_vec(std::size_t(s.n), g), y0 = random_vec(std::size_t(s.m * s.n), g);
        PackedLinear lin;
        lin.pack(w.data(), s.n, s.k, b.data(), prec);
        const std::string kernel = lin.kernel(s.m, accumulate, ldy);
        EXPECT_NE(kernel.rfind("ref", 0), 0u) << precision_name(prec) << " m=" << s.m << " n=" << s.n << " k=" << s.k
                                              << " acc=" << accumulate << ": " << kernel;
        std::vector<float> y(std::size_t(s.m * ldy), -7.f);
        for (int64_t i = 0; i < s.m; ++i)
          for (int64_t j = 0; j < s.n; ++j) y[i * ldy + j] = accumulate ? y0[i * s.n + j] : 123.f;
        lin.forward(x.data(), s.m, y.data(), accumulate, ldy);
        const auto want = reference(x, w, b, accumulate ? y0 : std::vector<float>{}, s.m, s.n, s.k, prec);
        double diff = 0;
        for (int64_t i = 0; i < s.m; ++i) {
          for (int64_t j = 0; j < s.n; ++j)
            diff = std::max(diff, std::fabs(double(y[i * ldy + j]) - want[i * s.n + j]));
          for (int64_t j = s.n; j < ldy; ++j) ASSERT_EQ(y[i * ldy + j], -7.f);  // columns past n untouched
        }
        EXPECT_LT(diff, 2e-5 * std::sqrt(double(s.k)))
            << precision_name(prec) << " m=" << s.m << " acc=" << accumulate;
        ++checked;
      }
    }
  }
  if (checked == 0) GTEST_SKIP() << "no precision runs on oneDNN here (TETHER_FP32_GEMM=onednn puts fp32 there)";
}

TEST(PackedLinear, PathFollowsTheCpu) {
  // bf16 is native exactly where the (capped) CPU and oneDNN both have bf16 instructions; fp16 always widens.
  EXPECT_EQ(linear_path(Precision::fp32), cpu_paths().fp32_panel ? LinearPath::panel_f32 : LinearPath::onednn_f32);
  EXPECT_EQ(linear_path(Precision::bf16), cpu_paths().native_bf16 ? LinearPath::onednn_bf16 : LinearPath::panel_bf16);
  EXPECT_EQ(linear_path(Precision::fp16), LinearPath::panel_f16);
  if (cpu_paths().effective < CpuIsa::avx512_bf16) {
    EXPECT_FALSE(cpu_paths().native_bf16);
    EXPECT_EQ(cpu_paths().bf16_dot_speed, 0.0);  // nothing to measure
  }
  // With AVX512-BF16 and no AMX the choice follows the measured speed of the bf16 dot product (unless overridden).
  if (cpu_paths().bf16_dot_speed > 0) {
    EXPECT_EQ(cpu_paths().effective, CpuIsa::avx512_bf16);
    EXPECT_EQ(cpu_paths().native_bf16, cpu_paths().bf16_dot_speed >= kMinNativeBf16Speed);
    EXPECT_LT(cpu_paths().bf16_dot_speed, 8.0);  // a real ratio, not a timer glitch
  }
  EXPECT_EQ(bf16_widened_reason().empty(), cpu_paths().native_bf16);
  EXPECT_EQ(parse_precision("fp16"), Precision::fp16);
  EXPECT_THROW(parse_precision("int3"), std::exception);
}

TEST(PackedLinear, RejectsMisuse) {
  PackedLinear lin;
  float x = 1, y = 0;
  EXPECT_THROW(lin.forward(&x, 1, &y), std::exception);
  EXPECT_THROW(lin.pack(&x, 0, 1, nullptr, Precision::fp32), std::exception);
}

// fp32 weights that are all bf16 values (a bf16 checkpoint widened) are kept as bf16 panels; the result must be
// bit-identical to the float32 panels of the same values.
TEST(PackedLinear, Fp32WeightsThatAreBf16ValuesGiveTheFloat32PanelsResultExactly) {
  if (linear_path(Precision::fp32) != LinearPath::panel_f32) GTEST_SKIP() << "fp32 runs on oneDNN here";
  const int64_t m = 37, n = 70, k = 300;
  std::mt19937 gen(7);
  std::uniform_real_distribution<float> dist(-1.0f, 1.0f);
  std::vector<float> x(static_cast<std::size_t>(m * k)), w(static_cast<std::size_t>(n * k)), b(static_cast<std::size_t>(n));
  for (auto& v : x) v = dist(gen);
  for (auto& v : w) v = bf16_to_f32(f32_to_bf16(dist(gen)));
  for (auto& v : b) v = dist(gen);
  PackedLinear lin;
  lin.pack(w.data(), n, k, b.data(), Precision::fp32);
  std::vector<float> y(std::size_t(m * n)), want(std::size_t(m * n));
  lin.forward(x.data(), m, y.data());
  const detail::PanelKernel& kernel = detail::panel_kernel();
  const auto panels = detail::pack_f32_panels(w.data(), n, k, kernel.panel_width);
  const std::vector<float> bias = detail::pad_bias(b.data(), n, kernel.panel_width);
  kernel.f32({x.data(), m, k, k, panels.data(), n, bias.data(), want.data(), n, false});
  EXPECT_EQ(y, want);
}
