// CPU backend kernels and GEMM against plain double-precision loops; prints max |diff| per case.
#include <gtest/gtest.h>
#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <functional>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "backend/cpu/gemm.h"
#include "backend/cpu/kernels.h"
#include "backend/float_math.h"
#include "core/error.h"

namespace tether::cpu {
namespace {

std::vector<float> random_vec(std::size_t n, uint32_t seed, float lo = -1.0f, float hi = 1.0f) {
  std::mt19937 gen(seed);
  std::uniform_real_distribution<float> dist(lo, hi);
  std::vector<float> v(n);
  for (auto& x : v) x = dist(gen);
  return v;
}

// Largest |got - want| over all elements, printed so a run shows how close each kernel is.
double max_diff(const std::string& name, const std::vector<float>& got, const std::vector<double>& want) {
  EXPECT_EQ(got.size(), want.size()) << name;
  double worst = 0.0;
  for (std::size_t i = 0; i < got.size() && i < want.size(); ++i) {
    const double d = std::abs(double(got[i]) - want[i]);
    if (!(d <= worst)) worst = d;  // also catches NaN
  }
  std::printf("[ max|diff| ] %-52s %.3e\n", name.c_str(), worst);
  return worst;
}

void expect_invalid(const std::function<void()>& fn) {
  try {
    fn();
    ADD_FAILURE() << "expected tether::Error";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::invalid_argument) << e.what();
  }
}

// ---------------------------------------------------------------- gemm / linear

TEST(Gemm, AllTransposesAlphaBetaAndStrides) {
  struct Case {
    int64_t m, n, k;
  };
  const Case cases[] = {{1, 1, 1}, {7, 13, 29}, {67, 45, 129}, {50, 320, 720}};
  uint32_t seed = 1;
  for (const Case& c : cases) {
    for (int ta = 0; ta < 2; ++ta) {
      for (int tb = 0; tb < 2; ++tb) {
        for (float beta : {0.0f, 1.0f, -0.5f}) {
          const float alpha = beta == 0.0f ? 1.0f : 0.75f;
          // Padded leading dimensions: each matrix lives inside a wider buffer.
          const int64_t a_rows = ta ? c.k : c.m, a_cols = ta ? c.m : c.k;
          const int64_t b_rows = tb ? c.n : c.k, b_cols = tb ? c.k : c.n;
          const int64_t lda = a_cols + 3, ldb = b_cols + 5, ldc = c.n + 2;
          auto a = random_vec(std::size_t(a_rows * lda), seed++);
          auto b = random_vec(std::size_t(b_rows * ldb), seed++);
          auto cm = random_vec(std::size_t(c.m * ldc), seed++);
          // With beta = 0 the old contents must be ignored, even NaN.
          if (beta == 0.0f) std::fill(cm.begin(), cm.end(), std::numeric_limits<float>::quiet_NaN());
          std::vector<double> want(cm.begin(), cm.end());
          for (int64_t i = 0; i < c.m; ++i) {
            for (int64_t j = 0; j < c.n; ++j) {
              double acc = 0.0;
              for (int64_t p = 0; p < c.k; ++p) {
                const double av = ta ? a[std::size_t(p * lda + i)] : a[std::size_t(i * lda + p)];
                const double bv = tb ? b[std::size_t(j * ldb + p)] : b[std::size_t(p * ldb + j)];
                acc += av * bv;
              }
              const double old = cm[std::size_t(i * ldc + j)];
              want[std::size_t(i * ldc + j)] = alpha * acc + (beta == 0.0f ? 0.0 : beta * old);
            }
          }
          const std::vector<float> before = cm;
          gemm(ta, tb, c.m, c.n, c.k, alpha, a.data(), lda, b.data(), ldb, beta, cm.data(), ldc);
          std::vector<float> got_mn;
          std::vector<double> want_mn;
          for (int64_t i = 0; i < c.m; ++i) {
            for (int64_t j = 0; j < ldc; ++j) {
              const std::size_t at = std::size_t(i * ldc + j);
              if (j < c.n) {
                got_mn.push_back(cm[at]);
                want_mn.push_back(want[at]);
              } else {  // the padding columns of C must be untouched (bitwise, NaN included)
                EXPECT_EQ(0, std::memcmp(&cm[at], &before[at], sizeof(float)));
              }
            }
          }
          const std::string name = "gemm " + std::to_string(c.m) + "x" + std::to_string(c.n) + "x" +
                                   std::to_string(c.k) + (ta ? " At" : " A") + (tb ? " Bt" : " B") +
                                   " beta=" + std::to_string(beta).substr(0, 4);
          EXPECT_LT(max_diff(name, got_mn, want_mn), 1e-5 * std::sqrt(double(c.k)) + 1e-6) << name;
        }
      }
    }
  }
}

TEST(Gemm, RejectsBadLeadingDimensions) {
  std::vector<float> buf(64);
  expect_invalid([&] { gemm(false, false, 4, 4, 4, 1.0f, buf.data(), 3, buf.data(), 4, 0.0f, buf.data(), 4); });
  expect_invalid([&] { gemm(true, false, 4, 2, 3, 1.0f, buf.data(), 3, buf.data(), 2, 0.0f, buf.data(), 2); });
  expect_invalid([&] { gemm(false, true, 4, 5, 3, 1.0f, buf.data(), 3, buf.data(), 2, 0.0f, buf.data(), 5); });
  expect_invalid([&] { gemm(false, false, 2, 5, 3, 1.0f, buf.data(), 3, buf.data(), 5, 0.0f, buf.data(), 4); });
  expect_invalid([&] { gemm(false, false, -1, 5, 3, 1.0f, buf.data(), 3, buf.data(), 5, 0.0f, buf.data(), 5); });
}

TEST(Linear, BiasAndAccumulateCombinations) {
  struct Case {
    int64_t m, k, n;
  };
  const Case cases[] = {{1, 33, 17}, {5, 64, 31}, {50, 720, 320}};
  uint32_t seed = 100;
  for (const Case& c : cases) {
    for (int with_bias = 0; with_bias < 2; ++with_bias) {
      for (int accumulate = 0; accumulate < 2; ++accumulate) {
        auto x = random_vec(std::size_t(c.m * c.k), seed++);
        auto w = random_vec(std::size_t(c.n * c.k), seed++);  // [N, K] like nn.Linear.weight
        auto bias = random_vec(std::size_t(c.n), seed++);
        auto y = random_vec(std::size_t(c.m * c.n), seed++);
        std::vector<double> want(y.size());
        for (int64_t i = 0; i < c.m; ++i) {
          for (int64_t j = 0; j < c.n; ++j) {
            double acc = with_bias ? bias[std::size_t(j)] : 0.0;
            for (int64_t p = 0; p < c.k; ++p)
              acc += double(x[std::size_t(i * c.k + p)]) * double(w[std::size_t(j * c.k + p)]);
            want[std::size_t(i * c.n + j)] = acc + (accumulate ? double(y[std::size_t(i * c.n + j)]) : 0.0);
          }
        }
        linear(x.data(), c.m, c.k, w.data(), with_bias ? bias.data() : nullptr, c.n, y.data(), accumulate);
        const std::string name = "linear " + std::to_string(c.m) + "x" + std::to_string(c.k) + "->" +
                                 std::to_string(c.n) + (with_bias ? " +bias" : "") + (accumulate ? " +=" : "");
        EXPECT_LT(max_diff(name, y, want), 1e-5 * std::sqrt(double(c.k)) + 1e-6) << name;
      }
    }
  }
}

TEST(Gemm, ReportsLibrary) {
  EXPECT_NE(std::string(blas_name()).find("oneDNN"), std::string::npos) << blas_name();
  EXPECT_GE(blas_threads(), 1);
  std::printf("[ blas       ] %s, %d threads\n", blas_name(), blas_threads());
}

// ---------------------------------------------------------------- norms

TEST(LayerNorm, MatchesReferenceIncludingLargeMean) {
  for (int64_t n : {1, 37, 768}) {
    for (float offset : {0.0f, 100.0f}) {
      const int64_t rows = 9;
      auto x = random_vec(std::size_t(rows * n), uint32_t(n) + 7);
      for (auto& v : x) v += offset;
      auto gamma = random_vec(std::size_t(n), 3, 0.5f, 1.5f), beta = random_vec(std::size_t(n), 4);
      const float eps = 1e-6f;
      std::vector<double> want(x.size());
      for (int64_t r = 0; r < rows; ++r) {
        double mean = 0, var = 0;
        for (int64_t i = 0; i < n; ++i) mean += x[std::size_t(r * n + i)];
        mean /= double(n);
        for (int64_t i = 0; i < n; ++i) var += std::pow(x[std::size_t(r * n + i)] - mean, 2);
        var /= double(n);
        for (int64_t i = 0; i < n; ++i)
          want[std::size_t(r * n + i)] =
              (x[std::size_t(r * n + i)] - mean) / std::sqrt(var + eps) * gamma[std::size_t(i)] + beta[std::size_t(i)];
      }
      std::vector<float> y(x.size());
      layer_norm(x.data(), rows, n, gamma.data(), beta.data(), eps, y.data());
      const std::string name = "layer_norm n=" + std::to_string(n) + " mean~" + std::to_string(int(offset));
      // With mean 100 the inputs themselves carry float rounding of ~4e-6 relative to a unit spread.
      EXPECT_LT(max_diff(name, y, want), offset == 0.0f ? 2e-6 : 1e-4) << name;
    }
  }
}

TEST(RmsNorm, MatchesReference) {
  for (int64_t n : {1, 17, 960}) {
    const int64_t rows = 6;
    auto x = random_vec(std::size_t(rows * n), uint32_t(n) + 21, -3.0f, 3.0f);
    auto w = random_vec(std::size_t(n), 22, 0.5f, 1.5f);
    const float eps = 1e-5f;
    std::vector<double> want(x.size());
    for (int64_t r = 0; r < rows; ++r) {
      double ms = 0;
      for (int64_t i = 0; i < n; ++i) ms += double(x[std::size_t(r * n + i)]) * x[std::size_t(r * n + i)];
      ms /= double(n);
      for (int64_t i = 0; i < n; ++i)
        want[std::size_t(r * n + i)] = x[std::size_t(r * n + i)] / std::sqrt(ms + eps) * w[std::size_t(i)];
    }
    std::vector<float> y(x.size());
    rms_norm(x.data(), rows, n, w.data(), eps, y.data());
    EXPECT_LT(max_diff("rms_norm n=" + std::to_string(n), y, want), 3e-6);
  }
}

// ---------------------------------------------------------------- rope

TEST(Rope, SplitHalvesWithFloat32Angles) {
  struct Case {
    int64_t batch, len, heads, dim;
  };
  for (const Case& c : {Case{2, 5, 3, 8}, Case{1, 7, 15, 64}, Case{3, 2, 5, 64}}) {
    const int64_t n = c.batch * c.len * c.heads * c.dim;
    auto x = random_vec(std::size_t(n), uint32_t(n));
    std::vector<int64_t> pos(std::size_t(c.batch * c.len));
    std::mt19937 gen(5);
    for (auto& p : pos) p = int64_t(gen() % 1200);
    pos[0] = 0;
    const float wavelength = 10000.0f;
    const int64_t half = c.dim / 2;
    // Upstream builds the angle in float32 (exponent, power, division), then rotates; the reference
    // repeats those float32 roundings and does the trigonometry and rotation in double.
    std::vector<double> want(static_cast<std::size_t>(n));
    for (int64_t t = 0; t < c.batch * c.len; ++t) {
      for (int64_t h = 0; h < c.heads; ++h) {
        const float* xr = x.data() + (t * c.heads + h) * c.dim;
        double* wr = want.data() + (t * c.heads + h) * c.dim;
        for (int64_t i = 0; i < half; ++i) {
          const float exponent = float(2.0 / double(c.dim)) * float(i);
          const float timescale = float(std::pow(double(wavelength), double(exponent)));
          const float radians = float(pos[std::size_t(t)]) / timescale;
          const double s = std::sin(double(radians)), co = std::cos(double(radians));
          wr[i] = xr[i] * co - double(xr[i + half]) * s;
          wr[i + half] = xr[i + half] * co + double(xr[i]) * s;
        }
      }
    }
    rope(x.data(), c.batch, c.len, c.heads, c.dim, pos.data(), wavelength);
    EXPECT_LT(max_diff("rope D=" + std::to_string(c.dim) + " H=" + std::to_string(c.heads), x, want), 5e-7);
  }
}

TEST(Rope, RejectsOddHeadDim) {
  std::vector<float> x(6);
  std::vector<int64_t> pos(1);
  expect_invalid([&] { rope(x.data(), 1, 1, 2, 3, pos.data(), 10000.0f); });
}

// ---------------------------------------------------------------- attention

struct AttnCase {
  std::string name;
  int64_t batch, len_q, len_k, heads, kv_heads, dim;
  int64_t q_pad = 0, kv_pad = 0;  // extra elements per token row: slices of a fused buffer
  int mask_kind = 0;               // 0 none, 1 random with special rows, 2 prefix-style (key j <= limit)
};

std::vector<double> attention_reference(const AttnCase& c, const float* q, int64_t q_stride, const float* k,
                                        const float* v, int64_t kv_stride, const std::vector<uint8_t>& mask,
                                        float scale) {
  const int64_t groups = c.heads / c.kv_heads;
  std::vector<double> out(std::size_t(c.batch * c.len_q * c.heads * c.dim));
  std::vector<double> s(std::size_t(c.len_k));
  for (int64_t b = 0; b < c.batch; ++b) {
    for (int64_t h = 0; h < c.heads; ++h) {
      const int64_t g = h / groups;
      for (int64_t i = 0; i < c.len_q; ++i) {
        const float* qr = q + (b * c.len_q + i) * q_stride + h * c.dim;
        double mx = -std::numeric_limits<double>::infinity();
        for (int64_t j = 0; j < c.len_k; ++j) {
          const float* kr = k + (b * c.len_k + j) * kv_stride + g * c.dim;
          double dot = 0;
          for (int64_t d = 0; d < c.dim; ++d) dot += double(qr[d]) * kr[d];
          const bool allowed = mask.empty() || mask[std::size_t((b * c.len_q + i) * c.len_k + j)];
          s[std::size_t(j)] = allowed ? dot * scale : double(std::numeric_limits<float>::lowest());
          mx = std::max(mx, s[std::size_t(j)]);
        }
        double sum = 0;
        for (auto& e : s) sum += (e = std::exp(e - mx));
        double* orow = out.data() + (b * c.len_q + i) * c.heads * c.dim + h * c.dim;
        for (int64_t j = 0; j < c.len_k; ++j) {
          const float* vr = v + (b * c.len_k + j) * kv_stride + g * c.dim;
          for (int64_t d = 0; d < c.dim; ++d) orow[d] += s[std::size_t(j)] / sum * vr[d];
        }
      }
    }
  }
  return out;
}

void run_attention_case(const AttnCase& c) {
  // q and k/v live in fused rows [q | pad] and [k | v | pad], as a fused projection would write them.
  const int64_t q_stride = c.heads * c.dim + c.q_pad;
  const int64_t kv_stride = 2 * c.kv_heads * c.dim + c.kv_pad;
  auto q = random_vec(std::size_t(c.batch * c.len_q * q_stride), 31, -2.0f, 2.0f);
  auto kv = random_vec(std::size_t(c.batch * c.len_k * kv_stride), 32, -2.0f, 2.0f);
  const float* k = kv.data();
  const float* v = kv.data() + c.kv_heads * c.dim;
  std::vector<uint8_t> mask;
  if (c.mask_kind != 0) {
    mask.resize(std::size_t(c.batch * c.len_q * c.len_k));
    std::mt19937 gen(33);
    for (int64_t b = 0; b < c.batch; ++b) {
      for (int64_t i = 0; i < c.len_q; ++i) {
        uint8_t* mr = mask.data() + (b * c.len_q + i) * c.len_k;
        for (int64_t j = 0; j < c.len_k; ++j) {
          mr[j] = c.mask_kind == 1 ? uint8_t(gen() % 3 != 0) : uint8_t(j <= (c.len_k - c.len_q) + i - b * 3);
        }
        if (c.mask_kind == 1 && i == 1) std::fill(mr, mr + c.len_k, 0);  // fully masked: uniform
        if (c.mask_kind == 1 && i == 2) {  // exactly one visible key
          std::fill(mr, mr + c.len_k, 0);
          mr[c.len_k - 1] = 1;
        }
      }
    }
  }
  const float scale = 1.0f / std::sqrt(float(c.dim));
  auto want = attention_reference(c, q.data(), q_stride, k, v, kv_stride, mask, scale);
  std::vector<float> out(want.size(), std::numeric_limits<float>::quiet_NaN());
  attention(q.data(), q_stride, k, v, kv_stride,
            mask.empty() ? nullptr : mask.data(), c.batch, c.len_q, c.len_k, c.heads, c.kv_heads, c.dim, scale,
            out.data());
  EXPECT_LT(max_diff("attention " + c.name, out, want), 2e-6) << c.name;

  if (c.mask_kind == 1) {
    // A fully masked row (item 0, query 1, head 0) is the plain mean of V over all keys.
    for (int64_t d = 0; d < c.dim; ++d) {
      double mean = 0;
      for (int64_t j = 0; j < c.len_k; ++j) mean += v[j * kv_stride + d];
      mean /= double(c.len_k);
      EXPECT_NEAR(out[std::size_t(1 * c.heads * c.dim + d)], mean, 1e-6);
    }
  }

  // Batch invariance: every item alone gives bit-identical rows to the batched call.
  if (c.batch > 1) {
    for (int64_t b = 0; b < c.batch; ++b) {
      std::vector<float> one(std::size_t(c.len_q * c.heads * c.dim));
      attention(q.data() + b * c.len_q * q_stride, q_stride, k + b * c.len_k * kv_stride,
                v + b * c.len_k * kv_stride, kv_stride,
                mask.empty() ? nullptr : mask.data() + b * c.len_q * c.len_k, 1, c.len_q, c.len_k, c.heads,
                c.kv_heads, c.dim, scale, one.data());
      EXPECT_EQ(0, std::memcmp(one.data(), out.data() + b * one.size(), one.size() * sizeof(float)))
          << c.name << " item " << b;
    }
  }
}

TEST(Attention, GqaStridedMaskedAndFullyMaskedRows) {
  run_attention_case({"gqa 6/2 B=2 7x13 D=16 strided random-mask", 2, 7, 13, 6, 2, 16, 5, 3, 1});
}

TEST(Attention, NoMaskOddLengthsAcrossBlocks) {
  run_attention_case({"mha 4/4 B=1 131x65 D=64 no-mask", 1, 131, 65, 4, 4, 64, 0, 0, 0});
}

TEST(Attention, ExpertShapeAgainstPrefix) {
  run_attention_case({"expert 15/5 B=2 50x173 D=64 prefix-mask", 2, 50, 173, 15, 5, 64, 0, 0, 2});
}

TEST(Attention, PrefixShapeSelfAttention) {
  run_attention_case({"prefix 15/5 B=1 113x113 D=64 prefix-mask", 1, 113, 113, 15, 5, 64, 0, 0, 2});
}

TEST(Attention, VisionShapeNoMask) {
  run_attention_case({"vision 12/12 B=1 256x256 D=64 no-mask", 1, 256, 256, 12, 12, 64, 0, 0, 0});
}

TEST(Attention, SameResultInsideAParallelRegion) {
  // Called from a worker thread, attention must run single-threaded and give identical numbers.
  const int64_t b = 1, lq = 20, lk = 40, h = 4, kvh = 2, d = 32;
  auto q = random_vec(std::size_t(b * lq * h * d), 41), k = random_vec(std::size_t(b * lk * kvh * d), 42);
  auto v = random_vec(std::size_t(b * lk * kvh * d), 43);
  std::vector<float> ref(std::size_t(b * lq * h * d)), inner(ref.size());
  attention(q.data(), h * d, k.data(), v.data(), kvh * d, nullptr, b, lq, lk, h, kvh, d, 0.125f, ref.data());
#pragma omp parallel num_threads(2)
  {
#pragma omp single
    attention(q.data(), h * d, k.data(), v.data(), kvh * d, nullptr, b, lq, lk, h, kvh, d, 0.125f, inner.data());
  }
  EXPECT_EQ(0, std::memcmp(ref.data(), inner.data(), ref.size() * sizeof(float)));
}

TEST(Attention, ABatchPackedInSeveralRunsGivesEachItemsOwnResult) {
  // 3 items x 12 K/V heads at 600 keys are more packed panels than attention holds at once (8 MB), so it packs and
  // runs them in turns: each item's result must still be the one it gets alone, bit for bit.
  const int64_t b = 3, len = 600, h = 12, d = 64, stride = h * d;
  auto q = random_vec(std::size_t(b * len * stride), 51), k = random_vec(std::size_t(b * len * stride), 52);
  auto v = random_vec(std::size_t(b * len * stride), 53);
  std::vector<float> all(q.size()), one(std::size_t(len * stride));
  attention(q.data(), stride, k.data(), v.data(), stride, nullptr, b, len, len, h, h, d, 0.125f, all.data());
  for (int64_t i = 0; i < b; ++i) {
    const std::size_t at = std::size_t(i * len * stride);
    attention(q.data() + at, stride, k.data() + at, v.data() + at, stride, nullptr, 1, len, len, h, h, d, 0.125f,
              one.data());
    EXPECT_EQ(0, std::memcmp(one.data(), all.data() + at, one.size() * sizeof(float))) << "item " << i;
  }
}

TEST(Attention, RejectsBadHeadsAndStrides) {
  std::vector<float> buf(1024);
  expect_invalid([&] {
    attention(buf.data(), 64, buf.data(), buf.data(), 32, nullptr, 1, 2, 2, 4, 3, 16, 1.0f, buf.data());
  });
  expect_invalid([&] {
    attention(buf.data(), 32, buf.data(), buf.data(), 32, nullptr, 1, 2, 2, 4, 2, 16, 1.0f, buf.data());
  });
  expect_invalid([&] {
    attention(buf.data(), 64, buf.data(), buf.data(), 16, nullptr, 1, 2, 2, 4, 2, 16, 1.0f, buf.data());
  });
}

// ---------------------------------------------------------------- softmax and activations

TEST(Softmax, RowsIncludingLargeAndEqualValues) {
  for (int64_t n : {1, 3, 1000}) {
    const int64_t rows = 5;
    auto x = random_vec(std::size_t(rows * n), uint32_t(n) + 50, -30.0f, 30.0f);
    for (int64_t i = 0; i < n; ++i) x[std::size_t(1 * n + i)] += 1e4f;  // shift invariance at large values
    std::fill(x.begin() + 2 * n, x.begin() + 3 * n, std::numeric_limits<float>::lowest());  // all "masked"
    std::vector<double> want(x.size());
    for (int64_t r = 0; r < rows; ++r) {
      double mx = -std::numeric_limits<double>::infinity(), sum = 0;
      for (int64_t i = 0; i < n; ++i) mx = std::max(mx, double(x[std::size_t(r * n + i)]));
      for (int64_t i = 0; i < n; ++i) sum += std::exp(x[std::size_t(r * n + i)] - mx);
      for (int64_t i = 0; i < n; ++i) want[std::size_t(r * n + i)] = std::exp(x[std::size_t(r * n + i)] - mx) / sum;
    }
    softmax_rows(x.data(), rows, n);
    EXPECT_LT(max_diff("softmax_rows n=" + std::to_string(n), x, want), 1e-6);
  }
}

double gelu_tanh_ref(double x) {
  const double u = std::sqrt(2.0 / M_PI) * (x + 0.044715 * x * x * x);
  return 0.5 * x * (1.0 + std::tanh(u));
}

double silu_ref(double x) { return x / (1.0 + std::exp(-x)); }

// Inputs spanning the ranges activations see, plus the tails where exp under/overflows.
std::vector<float> activation_inputs() {
  auto x = random_vec(4099, 60, -12.0f, 12.0f);
  for (float v : {0.0f, -0.0f, 1e-30f, -1e-30f, 50.0f, -50.0f, 100.0f, -100.0f, 1e4f, -1e4f, 3e38f, -3e38f})
    x.push_back(v);
  return x;
}

// Relative to max(1, |x|): the activations are about x-sized for large positive inputs.
double max_scaled_diff(const std::string& name, const std::vector<float>& got, const std::vector<double>& want,
                       const std::vector<float>& in) {
  double worst = 0;
  for (std::size_t i = 0; i < got.size(); ++i) {
    const double d = std::abs(got[i] - want[i]) / std::max(1.0, std::abs(double(in[i])));
    if (!(d <= worst)) worst = d;
  }
  std::printf("[ max|diff| ] %-52s %.3e (relative to max(1,|x|))\n", name.c_str(), worst);
  return worst;
}

TEST(Activations, GeluTanh) {
  auto x = activation_inputs();
  std::vector<double> want;
  for (float v : x) want.push_back(gelu_tanh_ref(v));
  auto y = x;
  gelu_tanh(y.data(), int64_t(y.size()));
  EXPECT_LT(max_scaled_diff("gelu_tanh", y, want, x), 5e-7);
  // A vector long enough to take the threaded path.
  auto big = random_vec(1 << 17, 61, -6.0f, 6.0f), big_in = big;
  gelu_tanh(big.data(), int64_t(big.size()));
  std::vector<double> big_want;
  for (float v : big_in) big_want.push_back(gelu_tanh_ref(v));
  EXPECT_LT(max_scaled_diff("gelu_tanh (threaded, 131072)", big, big_want, big_in), 5e-7);
}

TEST(Activations, SiluAndSiluMul) {
  auto x = activation_inputs();
  std::vector<double> want;
  for (float v : x) want.push_back(silu_ref(v));
  auto y = x;
  silu(y.data(), int64_t(y.size()));
  EXPECT_LT(max_scaled_diff("silu", y, want, x), 5e-7);

  auto up = random_vec(x.size(), 62, -3.0f, 3.0f);
  std::vector<double> want_mul;
  for (std::size_t i = 0; i < x.size(); ++i) want_mul.push_back(silu_ref(x[i]) * up[i]);
  std::vector<float> out(x.size());
  silu_mul(x.data(), up.data(), int64_t(x.size()), out.data());
  std::vector<float> scaled_in(x.size());
  for (std::size_t i = 0; i < x.size(); ++i) scaled_in[i] = x[i] * up[i];
  EXPECT_LT(max_scaled_diff("silu_mul", out, want_mul, scaled_in), 1e-6);
  auto alias = x;  // out may alias gate
  silu_mul(alias.data(), up.data(), int64_t(alias.size()), alias.data());
  EXPECT_EQ(0, std::memcmp(alias.data(), out.data(), out.size() * sizeof(float)));
}

#if defined(__x86_64__)
// The activations run a variant compiled for the dispatched ISA (AVX-512, or the AVX2 baseline under
// TETHER_MAX_CPU_ISA=AVX2, which the suite's second pass sets). Each must match, bit for bit, the same float32 steps
// done one element at a time here (built with -ffp-contract=off like the kernels, so nothing is fused).
TEST(Activations, DispatchedVariantMatchesScalarStepsBitForBit) {
  auto x = activation_inputs();
  const auto big = random_vec(1 << 17, 63, -8.0f, 8.0f);
  x.insert(x.end(), big.begin(), big.end());
  const auto up = random_vec(x.size(), 64, -3.0f, 3.0f);
  const std::size_t n = x.size();
  auto gelu_one = [](float v) {
    const float inner = float(0.79788456080286535588) * (v + 0.044715f * (v * v * v));
    return 0.5f * v * (1.0f + tether::float_math::tanh_f32(inner));
  };
  auto silu_one = [](float v) { return v / (1.0f + tether::float_math::exp_f32(-v)); };
  std::vector<float> want_gelu(n), want_gelu_mul(n), want_silu(n), want_silu_mul(n);
  for (std::size_t i = 0; i < n; ++i) {
    want_gelu[i] = gelu_one(x[i]);
    want_gelu_mul[i] = want_gelu[i] * up[i];
    want_silu[i] = silu_one(x[i]);
    want_silu_mul[i] = want_silu[i] * up[i];
  }
  auto same = [n](const std::vector<float>& a, const std::vector<float>& b) {
    return std::memcmp(a.data(), b.data(), n * sizeof(float)) == 0;
  };
  auto g = x, s = x;
  gelu_tanh(g.data(), int64_t(n));
  silu(s.data(), int64_t(n));
  std::vector<float> gm(n), sm(n);
  gelu_tanh_mul(x.data(), up.data(), int64_t(n), gm.data());
  silu_mul(x.data(), up.data(), int64_t(n), sm.data());
  EXPECT_TRUE(same(g, want_gelu));
  EXPECT_TRUE(same(gm, want_gelu_mul));
  EXPECT_TRUE(same(s, want_silu));
  EXPECT_TRUE(same(sm, want_silu_mul));

  // softmax_row's exponentials (the max and the lane sum are the same on every ISA by construction).
  auto row = random_vec(1000, 65, -20.0f, 20.0f);
  float mx = row[0];
  for (float v : row) mx = std::max(mx, v);
  std::vector<float> e(row.size());
  for (std::size_t i = 0; i < row.size(); ++i) e[i] = tether::float_math::exp_f32(row[i] - mx);
  float lanes[8] = {};
  for (std::size_t i = 0; i < e.size(); ++i) lanes[i % 8] += e[i];
  const float inv = 1.0f / (((lanes[0] + lanes[1]) + (lanes[2] + lanes[3])) + ((lanes[4] + lanes[5]) + (lanes[6] + lanes[7])));
  softmax_row(row.data(), int64_t(row.size()), nullptr);
  for (std::size_t i = 0; i < row.size(); ++i) ASSERT_EQ(row[i], e[i] * inv) << i;
}
#endif

TEST(Activations, SpecialValues) {
  std::vector<float> x = {0.0f, -100.0f, 100.0f, std::numeric_limits<float>::quiet_NaN()};
  auto g = x, s = x;
  gelu_tanh(g.data(), 4);
  silu(s.data(), 4);
  EXPECT_EQ(g[0], 0.0f);
  EXPECT_EQ(s[0], 0.0f);
  EXPECT_NEAR(g[1], 0.0f, 1e-30f);
  EXPECT_NEAR(s[1], 0.0f, 1e-30f);
  EXPECT_EQ(g[2], 100.0f);
  EXPECT_EQ(s[2], 100.0f);
  EXPECT_TRUE(std::isnan(g[3]));
  EXPECT_TRUE(std::isnan(s[3]));
}

TEST(Elementwise, AddAndScaleWithAliasing) {
  for (int64_t n : {int64_t(1), int64_t(1001), int64_t(1) << 17}) {
    auto a = random_vec(std::size_t(n), 70), b = random_vec(std::size_t(n), 71);
    std::vector<double> sum(static_cast<std::size_t>(n)), scaled(static_cast<std::size_t>(n));
    for (int64_t i = 0; i < n; ++i) {
      sum[std::size_t(i)] = double(a[std::size_t(i)]) + b[std::size_t(i)];
      scaled[std::size_t(i)] = double(a[std::size_t(i)]) * 0.3;
    }
    std::vector<float> out(static_cast<std::size_t>(n));
    add(a.data(), b.data(), n, out.data());
    EXPECT_LT(max_diff("add n=" + std::to_string(n), out, sum), 1.2e-7);
    auto alias = a;
    add(alias.data(), b.data(), n, alias.data());
    EXPECT_EQ(alias, out);
    scale(a.data(), n, 0.3f);
    EXPECT_LT(max_diff("scale n=" + std::to_string(n), a, scaled), 1.2e-7);
  }
}

// ---------------------------------------------------------------- patch embedding

TEST(PatchEmbed, MatchesDirectConvolution) {
  const int64_t batch = 2, ch = 3, height = 8, width = 12, patch = 4, embed = 5;
  auto pixels = random_vec(std::size_t(batch * ch * height * width), 80);
  auto w = random_vec(std::size_t(embed * ch * patch * patch), 81);
  auto bias = random_vec(std::size_t(embed), 82);
  const int64_t ph = height / patch, pw = width / patch;
  std::vector<double> want(std::size_t(batch * ph * pw * embed));
  for (int64_t b = 0; b < batch; ++b)
    for (int64_t py = 0; py < ph; ++py)
      for (int64_t px = 0; px < pw; ++px)
        for (int64_t e = 0; e < embed; ++e) {
          double acc = bias[std::size_t(e)];
          for (int64_t c = 0; c < ch; ++c)
            for (int64_t ky = 0; ky < patch; ++ky)
              for (int64_t kx = 0; kx < patch; ++kx)
                acc += double(pixels[std::size_t(((b * ch + c) * height + py * patch + ky) * width + px * patch + kx)]) *
                       w[std::size_t(((e * ch + c) * patch + ky) * patch + kx)];
          want[std::size_t(((b * ph + py) * pw + px) * embed + e)] = acc;
        }
  std::vector<float> out(want.size());
  patch_embed(pixels.data(), batch, ch, height, width, w.data(), bias.data(), embed, patch, out.data());
  EXPECT_LT(max_diff("patch_embed 2x3x8x12 p=4 e=5", out, want), 2e-6);
  expect_invalid(
      [&] { patch_embed(pixels.data(), 1, ch, 9, width, w.data(), bias.data(), embed, patch, out.data()); });
}

// ---------------------------------------------------------------- pixel shuffle

// A contiguous tensor with the two operations the upstream sequence uses, done literally: a view
// reinterprets the same buffer under a new shape; a permute materialises the transposed order.
struct Nd {
  std::vector<int64_t> shape;
  std::vector<float> data;

  Nd view(std::vector<int64_t> s) const {
    int64_t n = 1;
    for (int64_t d : s) n *= d;
    EXPECT_EQ(n, int64_t(data.size()));
    return {std::move(s), data};
  }
  Nd permute(const std::vector<int>& order) const {
    Nd out;
    for (int d : order) out.shape.push_back(shape[std::size_t(d)]);
    out.data.resize(data.size());
    std::vector<int64_t> in_strides(shape.size(), 1);
    for (int d = int(shape.size()) - 2; d >= 0; --d)
      in_strides[std::size_t(d)] = in_strides[std::size_t(d + 1)] * shape[std::size_t(d + 1)];
    std::vector<int64_t> idx(shape.size(), 0);  // multi-index into out
    for (std::size_t flat = 0; flat < out.data.size(); ++flat) {
      int64_t src = 0;
      for (std::size_t d = 0; d < idx.size(); ++d) src += idx[d] * in_strides[std::size_t(order[d])];
      out.data[flat] = data[std::size_t(src)];
      for (int d = int(idx.size()) - 1; d >= 0; --d) {
        if (++idx[std::size_t(d)] < out.shape[std::size_t(d)]) break;
        idx[std::size_t(d)] = 0;
      }
    }
    return out;
  }
};

TEST(PixelShuffle, MatchesUpstreamViewPermuteSequence) {
  struct Case {
    int64_t batch, seq, embed, r;
  };
  for (const Case& c : {Case{1, 16, 3, 2}, Case{2, 36, 2, 3}, Case{2, 1024, 5, 4}, Case{1, 4, 1, 1}}) {
    Nd x{{c.batch, c.seq, c.embed}, {}};
    x.data.resize(std::size_t(c.batch * c.seq * c.embed));
    for (std::size_t i = 0; i < x.data.size(); ++i) x.data[i] = float(i);  // every element distinct
    const int64_t side = int64_t(std::lround(std::sqrt(double(c.seq))));
    // The Idefics3 connector's sequence of shapes, step by step.
    Nd t = x.view({c.batch, side, side, c.embed});
    t = t.view({c.batch, side, side / c.r, c.embed * c.r});
    t = t.permute({0, 2, 1, 3});
    t = t.view({c.batch, side / c.r, side / c.r, c.embed * c.r * c.r});
    t = t.permute({0, 2, 1, 3});
    t = t.view({c.batch, c.seq / (c.r * c.r), c.embed * c.r * c.r});

    std::vector<float> out(x.data.size());
    pixel_shuffle(x.data.data(), c.batch, c.seq, c.embed, c.r, out.data());
    EXPECT_EQ(out, t.data) << "seq=" << c.seq << " r=" << c.r;
    std::printf("[ exact      ] pixel_shuffle B=%lld seq=%lld E=%lld r=%lld: %s\n", (long long)c.batch,
                (long long)c.seq, (long long)c.embed, (long long)c.r, out == t.data ? "identical" : "DIFFERENT");
  }
  std::vector<float> buf(64);
  expect_invalid([&] { pixel_shuffle(buf.data(), 1, 15, 1, 1, buf.data()); });
  expect_invalid([&] { pixel_shuffle(buf.data(), 1, 36, 1, 4, buf.data()); });
}

}  // namespace
}  // namespace tether::cpu
