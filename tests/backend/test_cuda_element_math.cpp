// The CUDA kernels' per-element arithmetic (src/backend/cuda/element_math.h), run on the host: against float64
// references, and to the bit against the CPU backend where the two are meant to agree exactly. Built and run in every
// build, GPU or not.
#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <limits>
#include <random>
#include <vector>

#include "backend/cuda/element_math.h"
#include "core/dtype.h"

namespace tether::cuda_math {
namespace {

uint32_t bits(float f) {
  uint32_t b;
  std::memcpy(&b, &f, 4);
  return b;
}

// Distance in units in the last place between two finite floats of the same sign (0 when equal, +0 == -0).
int64_t ulps(float a, float b) { return a == b ? 0 : std::abs(int64_t(bits(a)) - int64_t(bits(b))); }

std::vector<float> sweep(float lo, float hi, int count) {
  std::vector<float> v;
  for (int i = 0; i <= count; ++i) v.push_back(lo + (hi - lo) * float(i) / float(count));
  for (float special : {0.0f, -0.0f, 1e-30f, -1e-30f, 88.7f, -87.4f, 100.0f, -100.0f}) v.push_back(special);
  return v;
}

// The shared polynomial exp and tanh (backend/float_math.h) that the device runs, within 2 ulp of float64.
TEST(CudaElementMath, ExpAndTanhWithinTwoUlp) {
  for (float x : sweep(-87, 88, 200001)) {
    if (x < -87.33f) continue;  // below ln(FLT_MIN) the result is flushed to 0 (documented), not a denormal
    const float e = exp_f32(x), want_e = float(std::exp(double(x)));
    ASSERT_LE(ulps(e, want_e), 2) << x;
    const float t = tanh_f32(x), want_t = float(std::tanh(double(x)));
    ASSERT_LE(ulps(t, want_t), 2) << x;
  }
  EXPECT_TRUE(std::isnan(exp_f32(std::numeric_limits<float>::quiet_NaN())));
  EXPECT_EQ(exp_f32(std::numeric_limits<float>::infinity()), std::numeric_limits<float>::infinity());
  EXPECT_EQ(exp_f32(-std::numeric_limits<float>::infinity()), 0.0f);
}

TEST(CudaElementMath, ActivationsAgainstFloat64) {
  double worst[4] = {}, largest[4] = {};
  for (float x : sweep(-12, 12, 100001)) {
    const double v = x;
    const double want[4] = {v / (1 + std::exp(-v)),
                            0.5 * v * (1 + std::tanh(std::sqrt(2 / M_PI) * (v + 0.044715 * v * v * v))),
                            0.5 * v * (1 + std::erf(v / std::sqrt(2.0))), std::max(0.0, v)};
    for (int a = 0; a < 4; ++a) {
      const double got = activate(Act(a), x);
      worst[a] = std::max(worst[a], std::abs(got - want[a]));
      largest[a] = std::max(largest[a], std::abs(want[a]));
    }
  }
  // Relative to the largest magnitude, as test_backend_ops measures (1 + tanh cancels far out on the negative side).
  for (int a = 0; a < 4; ++a) worst[a] /= largest[a];
  const char* names[4] = {"silu", "gelu_tanh", "gelu_erf", "relu"};
  for (int a = 0; a < 4; ++a) {
    std::printf("[ rel|diff| ] %-20s %.3e\n", names[a], worst[a]);
    EXPECT_LT(worst[a], 1e-6) << names[a];
  }
  // A gated element rounds the activation to float32 before the product, as upstream's two tensors do.
  EXPECT_EQ(bits(gated(Act::gelu_tanh, 0.7f, 1.3f)), bits(gelu_tanh(0.7f) * 1.3f));
}

TEST(CudaElementMath, HalfTypesConvertExactlyAsTheCore) {
  for (uint32_t h = 0; h < 65536; ++h) {
    const float b = bf16_bits_to_float(uint16_t(h)), f = f16_bits_to_float(uint16_t(h));
    const float want_b = bf16_to_f32(uint16_t(h)), want_f = f16_to_f32(uint16_t(h));
    if (std::isnan(want_b)) ASSERT_TRUE(std::isnan(b)) << h;
    else ASSERT_EQ(bits(b), bits(want_b)) << h;
    if (std::isnan(want_f)) ASSERT_TRUE(std::isnan(f)) << h;
    else ASSERT_EQ(bits(f), bits(want_f)) << h;
  }
  std::mt19937 gen(5);
  for (int i = 0; i < 200000; ++i) {
    const uint32_t b = gen();
    float x;
    std::memcpy(&x, &b, 4);
    if (std::isnan(x)) ASSERT_TRUE(std::isnan(bf16_bits_to_float(float_to_bf16_bits(x))));
    else ASSERT_EQ(float_to_bf16_bits(x), f32_to_bf16(x)) << x;
  }
}

TEST(CudaElementMath, NormsAgainstFloat64) {
  std::mt19937 gen(7);
  std::normal_distribution<float> dist(0.3f, 2.0f);
  const int64_t n = 960;
  std::vector<float> x(n), w(n);
  for (auto& v : x) v = dist(gen);
  for (auto& v : w) v = dist(gen);
  double sum = 0, squares = 0;
  for (float v : x) sum += v, squares += double(v) * v;
  const double mean = sum / n;
  double centred = 0;
  for (float v : x) centred += (v - mean) * (v - mean);
  const float eps = 1e-6f;
  const float inv = rms_inverse(squares, n, eps);
  const LayerNormStats stats = layer_norm_stats(mean, centred, n, eps);
  double worst_rms = 0, worst_ln = 0;
  for (int64_t i = 0; i < n; ++i) {
    const double r = x[i] / std::sqrt(squares / n + eps);
    worst_rms = std::max({worst_rms, std::abs(rms_apply(x[i], inv, w[i], 0) - r * w[i]),
                          std::abs(rms_apply(x[i], inv, w[i], 1) - r * (1.0 + w[i])), std::abs(rms_apply(x[i], inv, 0, 2) - r)});
    const double l = (x[i] - mean) / std::sqrt(centred / n + eps);
    worst_ln = std::max(worst_ln, std::abs(layer_norm_apply(x[i], stats, w.data(), nullptr, i) - l * w[i]));
  }
  EXPECT_LT(worst_rms, 1e-5);
  EXPECT_LT(worst_ln, 1e-5);
}

// The running softmax over 32-key blocks against a float64 softmax, for rows whose first blocks are all masked, rows
// with nothing kept (uniform over every key, as the reference), and a row whose padding lanes are out of range.
TEST(CudaElementMath, OnlineSoftmaxMatchesTheReferenceRule) {
  std::mt19937 gen(11);
  std::uniform_real_distribution<float> dist(-30, 30);
  for (int pattern = 0; pattern < 4; ++pattern) {
    const int64_t len = 77;
    std::vector<float> dots(len);
    std::vector<bool> keep(len);
    for (int64_t j = 0; j < len; ++j) {
      dots[j] = dist(gen);
      keep[j] = pattern == 0 ? true : pattern == 1 ? j >= 40 : pattern == 2 ? false : (j % 3 != 0);
    }
    OnlineSoftmax state = online_softmax_start();
    std::vector<double> weight(len);
    for (int64_t key0 = 0; key0 < len; key0 += 32) {
      float block_max = -std::numeric_limits<float>::infinity();
      std::vector<float> score(32, -std::numeric_limits<float>::infinity());
      for (int64_t j = key0; j < std::min(len, key0 + 32); ++j)
        block_max = std::max(block_max, score[j - key0] = masked_score(dots[j], 0.125f, keep[j]));
      const float factor = online_softmax_rescale(state, block_max);
      for (int64_t j = 0; j < key0; ++j) weight[j] *= factor;
      for (int64_t j = key0; j < std::min(len, key0 + 32); ++j) state.sum += float(weight[j] = online_softmax_weight(state, score[j - key0]));
    }
    bool any = false;
    for (bool k : keep) any = any || k;
    double mx = -1e300, total = 0;
    for (int64_t j = 0; j < len; ++j)
      if (keep[j] || !any) mx = std::max(mx, keep[j] ? dots[j] * 0.125 : 0.0);
    std::vector<double> want(len);
    for (int64_t j = 0; j < len; ++j) total += want[j] = !any ? 1.0 : keep[j] ? std::exp(dots[j] * 0.125 - mx) : 0.0;
    for (int64_t j = 0; j < len; ++j) {
      ASSERT_NEAR(weight[j] / state.sum, want[j] / total, 2e-6) << "pattern " << pattern << " key " << j;
      if (any && !keep[j]) {
        ASSERT_EQ(weight[j], 0.0) << "a masked key kept weight, pattern " << pattern;
      }
    }
  }
}

TEST(CudaElementMath, RotaryAnglesRoundAsTheCpuBackend) {
  // The three angle conventions against their float64 definitions; timescales are the correctly rounded powers.
  for (int angles = 0; angles < 3; ++angles)
    for (int64_t head_dim : {64, 256})
      for (int64_t i = 0; i < head_dim / 2; ++i) {
        const float ts = rope_timescale(i, head_dim, 10000.0f, angles);
        const double exact = std::pow(10000.0, 2.0 * double(i) / double(head_dim));
        const double want = angles == 0 ? exact : 1.0 / exact;
        ASSERT_NEAR(ts, want, (angles == 2 ? 4e-3 : 2e-7) * want) << angles << " " << i;
        const float pos = 123.0f;
        ASSERT_EQ(rope_angle(pos, ts, angles), angles == 0 ? pos / ts : pos * ts);
      }
  float a = 0.3f, b = -1.7f;
  rotate_pair(a, b, std::cos(0.4f), std::sin(0.4f));
  EXPECT_NEAR(a, 0.3 * std::cos(0.4) + 1.7 * std::sin(0.4), 1e-6);
  EXPECT_NEAR(b, -1.7 * std::cos(0.4) + 0.3 * std::sin(0.4), 1e-6);
}

TEST(CudaElementMath, SamplerStepIsExact) {
  EXPECT_EQ(bits(axpy(0.25f, -0.1f, 3.7f)), bits(0.25f + -0.1f * 3.7f));
  const float x = 0.4f, v = -1.2f, target = 0.9f, w = 0.75f, t = 0.6f, gw = 3.5f;
  const float err = (target - (x - t * v)) * w;
  EXPECT_EQ(bits(rtc_guide(x, v, target, w, t, gw)), bits(v - gw * err));
  float s, c;
  time_embedding_pair(0.7, 3, 360, 4e-3, 4.0, s, c);
  const double period = 4e-3 * std::pow(1000.0, 3.0 / 359.0);
  EXPECT_EQ(s, float(std::sin(2 * M_PI * 0.7 / period)));
  EXPECT_NEAR(c, std::cos(2 * M_PI * 0.7 / period), 1e-7);
}

}  // namespace
}  // namespace tether::cuda_math
