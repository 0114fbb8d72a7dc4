// Every operation of the backend interface, on every compiled backend, against a plain double-precision reference at
// the widths the families use (SmolVLA's SmolVLM/SmolLM2 and expert, pi0's Gemma and SigLIP). Data goes in and out
// through the backend's own upload/download, so the memory side of the interface is exercised too. CTest runs it
// natively and again with TETHER_MAX_CPU_ISA=AVX2.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <cstring>
#include <functional>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "backend/backend.h"
#include "core/error.h"
#include "cuda_math_backend.h"

namespace tether::backend {
namespace {

std::vector<float> random_vec(int64_t n, uint32_t seed, float lo = -1.0f, float hi = 1.0f) {
  std::mt19937 gen(seed);
  std::uniform_real_distribution<float> dist(lo, hi);
  std::vector<float> v(static_cast<std::size_t>(n));
  for (auto& x : v) x = dist(gen);
  return v;
}

// Relative to the reference's largest magnitude, printed so a run shows how close each op is.
double rel_diff(const std::string& name, const std::vector<float>& got, const std::vector<double>& want) {
  EXPECT_EQ(got.size(), want.size()) << name;
  double worst = 0, scale = 1e-30;
  for (std::size_t i = 0; i < got.size() && i < want.size(); ++i) {
    const double d = std::abs(double(got[i]) - want[i]);
    if (!(d <= worst)) worst = d;  // also catches NaN
    scale = std::max(scale, std::abs(want[i]));
  }
  std::printf("[ rel|diff| ] %-58s %.3e\n", name.c_str(), worst / scale);
  return worst / scale;
}

class BackendOps : public ::testing::TestWithParam<std::string> {
 protected:
  void SetUp() override {
    if (GetParam() == "cuda_math_on_host") {
      be = make_cuda_math_on_host_backend();
      return;
    }
    std::string why;
    if (!backend_usable(GetParam(), &why)) GTEST_SKIP() << "skipped: " << why;
    be = make_backend(GetParam());
  }
  template <typename T>
  Array<T> put(const std::vector<T>& host) {
    Array<T> a = be->alloc<T>(int64_t(host.size()));
    be->upload(host.data(), int64_t(host.size()), a.at());
    return a;
  }
  template <typename T>
  std::vector<T> get(const Array<T>& a, int64_t n = -1) {
    std::vector<T> host(std::size_t(n < 0 ? a.size() : n));
    be->download(Ptr<const T>(a.at()), int64_t(host.size()), host.data());
    return host;
  }
  std::string label(const std::string& op) const { return GetParam() + " " + op; }
  std::shared_ptr<Backend> be;
};

// (rows, in, out) of linear layers the families run: SmolVLA q|k|v, expert MLP, pi0 Gemma q|k|v (MQA, head_dim 256)
// and GeGLU, SigLIP-so400m fc1.
struct LinearShape {
  int64_t m, k, n;
};
const LinearShape kLinearShapes[] = {{13, 960, 960 + 2 * 320}, {50, 720, 2 * 2048}, {7, 2048, 2048 + 2 * 256},
                                     {9, 1024, 2 * 4096},      {5, 1152, 4304},     {1, 32, 960}};

TEST_P(BackendOps, Linear) {
  for (const auto& [m, k, n] : kLinearShapes) {
    const auto w = random_vec(n * k, 1), b = random_vec(n, 2), x = random_vec(m * k, 3), y0 = random_vec(m * n, 4);
    auto lw = be->pack_linear(w.data(), n, k, b.data(), cpu::Precision::fp32);
    EXPECT_EQ(lw->out_features(), n);
    EXPECT_EQ(lw->in_features(), k);
    for (bool accumulate : {false, true}) {
      const Array<float> xa = put(x), ya = put(y0);
      const double before = be->flops().linear;
      be->linear(*lw, xa.at(), m, ya.at(), accumulate);
      EXPECT_DOUBLE_EQ(be->flops().linear - before, 2.0 * double(m * n * k));
      std::vector<double> want(static_cast<std::size_t>(m * n));
      for (int64_t r = 0; r < m; ++r)
        for (int64_t j = 0; j < n; ++j) {
          double acc = b[j];
          for (int64_t i = 0; i < k; ++i) acc += double(x[r * k + i]) * double(w[j * k + i]);
          want[r * n + j] = acc + (accumulate ? y0[r * n + j] : 0.0);
        }
      EXPECT_LT(rel_diff(label("linear " + std::to_string(m) + "x" + std::to_string(k) + "x" + std::to_string(n) +
                               (accumulate ? " +=" : "")),
                         get(ya), want),
                1e-5);
    }
  }
  // A strided output lands in the first columns of a wider buffer and leaves the rest alone.
  const int64_t m = 4, k = 48, n = 16, ldy = 40;
  const auto w = random_vec(n * k, 5), x = random_vec(m * k, 6), y0 = random_vec(m * ldy, 7);
  auto lw = be->pack_linear(w.data(), n, k, nullptr, cpu::Precision::fp32);
  const Array<float> xa = put(x), ya = put(y0);
  be->linear(*lw, xa.at(), m, ya.at(), false, ldy);
  const auto y = get(ya);
  for (int64_t r = 0; r < m; ++r)
    for (int64_t j = n; j < ldy; ++j) EXPECT_EQ(y[r * ldy + j], y0[r * ldy + j]);
}

TEST_P(BackendOps, HalfPrecisionLinearStaysClose) {
  const int64_t m = 6, k = 960, n = 320;
  const auto w = random_vec(n * k, 8), x = random_vec(m * k, 9);
  for (cpu::Precision p : {cpu::Precision::bf16, cpu::Precision::fp16}) {
    auto lw = be->pack_linear(w.data(), n, k, nullptr, p);
    const Array<float> xa = put(x), ya = be->alloc<float>(m * n);
    be->linear(*lw, xa.at(), m, ya.at());
    std::vector<double> want(static_cast<std::size_t>(m * n));
    for (int64_t r = 0; r < m; ++r)
      for (int64_t j = 0; j < n; ++j) {
        double acc = 0;
        for (int64_t i = 0; i < k; ++i) acc += double(x[r * k + i]) * double(w[j * k + i]);
        want[r * n + j] = acc;
      }
    EXPECT_LT(rel_diff(label(std::string("linear ") + cpu::precision_name(p)), get(ya), want), 2e-2);
  }
}

TEST_P(BackendOps, Norms) {
  for (int64_t n : {int64_t(720), int64_t(960), int64_t(1152), int64_t(2048)}) {
    const int64_t rows = 7;
    const auto x = random_vec(rows * n, 10, -3, 3), w = random_vec(n, 11), beta = random_vec(n, 12);
    const Array<float> xa = put(x), wa = put(w), ba = put(beta), ya = be->alloc<float>(rows * n);
    const float eps = 1e-6f;
    std::vector<double> rms(static_cast<std::size_t>(rows)), mean(static_cast<std::size_t>(rows)), var(static_cast<std::size_t>(rows));
    for (int64_t r = 0; r < rows; ++r) {
      double sq = 0, s = 0;
      for (int64_t i = 0; i < n; ++i) sq += double(x[r * n + i]) * x[r * n + i], s += x[r * n + i];
      rms[r] = 1.0 / std::sqrt(sq / double(n) + eps);
      mean[r] = s / double(n);
      double v = 0;
      for (int64_t i = 0; i < n; ++i) v += (x[r * n + i] - mean[r]) * (x[r * n + i] - mean[r]);
      var[r] = v / double(n);
    }
    std::vector<double> want(static_cast<std::size_t>(rows * n));
    const std::string size = " n=" + std::to_string(n);
    for (RmsScale kind : {RmsScale::weight, RmsScale::one_plus_weight}) {
      be->rms_norm(xa.at(), rows, n, wa.at(), eps, ya.at(), kind);
      for (int64_t r = 0; r < rows; ++r)
        for (int64_t i = 0; i < n; ++i)
          want[r * n + i] = x[r * n + i] * rms[r] * (kind == RmsScale::weight ? w[i] : 1.0 + w[i]);
      EXPECT_LT(rel_diff(label(kind == RmsScale::weight ? "rms_norm" : "rms_norm (1+w)") + size, get(ya), want), 1e-6);
    }
    be->layer_norm(xa.at(), rows, n, wa.at(), ba.at(), eps, ya.at());
    for (int64_t r = 0; r < rows; ++r)
      for (int64_t i = 0; i < n; ++i)
        want[r * n + i] = (x[r * n + i] - mean[r]) / std::sqrt(var[r] + eps) * w[i] + beta[i];
    EXPECT_LT(rel_diff(label("layer_norm") + size, get(ya), want), 1e-6);

    // Adaptive: two conditioning groups over the rows (rows 0..3 and 4..6 with rows_per_group 4).
    // The modulation rows are [scale | shift | gate], as an adaptive norm's dense layer writes them.
    const auto mod = random_vec(2 * 3 * n, 13);
    const Array<float> ma = put(mod);
    be->rms_norm_modulated(xa.at(), rows, n, ma.at(), ma.at(n), 3 * n, 4, eps, ya.at());
    for (int64_t r = 0; r < rows; ++r)
      for (int64_t i = 0; i < n; ++i)
        want[r * n + i] = x[r * n + i] * rms[r] * (1.0 + mod[(r / 4) * 3 * n + i]) + mod[(r / 4) * 3 * n + n + i];
    EXPECT_LT(rel_diff(label("rms_norm_modulated") + size, get(ya), want), 1e-6);

    // An adaptive LayerNorm: LayerNorm without affine, then modulate in place (GR00T's DiT).
    be->layer_norm(xa.at(), rows, n, Ptr<const float>(), Ptr<const float>(), eps, ya.at());
    be->modulate(ya.at(), rows, n, ma.at(), ma.at(n), 3 * n, 4);
    for (int64_t r = 0; r < rows; ++r)
      for (int64_t i = 0; i < n; ++i)
        want[r * n + i] = (x[r * n + i] - mean[r]) / std::sqrt(var[r] + eps) * (1.0 + mod[(r / 4) * 3 * n + i]) +
                          mod[(r / 4) * 3 * n + n + i];
    EXPECT_LT(rel_diff(label("layer_norm + modulate") + size, get(ya), want), 1e-6);
  }
}

// Reference masked attention, double precision; masked scores take no weight; a fully masked row is uniform.
std::vector<double> reference_attention(const std::vector<float>& q, int64_t qs, const std::vector<float>& k,
                                        const std::vector<float>& v, int64_t kvs, const std::vector<uint8_t>* mask,
                                        int64_t B, int64_t Lq, int64_t Lk, int64_t H, int64_t KvH, int64_t D,
                                        double scale) {
  std::vector<double> out(static_cast<std::size_t>(B * Lq * H * D));
  for (int64_t b = 0; b < B; ++b)
    for (int64_t h = 0; h < H; ++h) {
      const int64_t g = h / (H / KvH);
      for (int64_t i = 0; i < Lq; ++i) {
        std::vector<double> s(static_cast<std::size_t>(Lk));
        double mx = -1e300;
        bool any = false;
        for (int64_t j = 0; j < Lk; ++j) {
          const bool keep = !mask || (*mask)[(b * Lq + i) * Lk + j];
          any = any || keep;
          double dot = 0;
          for (int64_t d = 0; d < D; ++d) dot += double(q[(b * Lq + i) * qs + h * D + d]) * k[(b * Lk + j) * kvs + g * D + d];
          s[j] = keep ? dot * scale : -1e300;
          mx = std::max(mx, s[j]);
        }
        double sum = 0;
        for (int64_t j = 0; j < Lk; ++j) sum += (s[j] = any ? (s[j] == -1e300 ? 0 : std::exp(s[j] - mx)) : 1.0);
        for (int64_t d = 0; d < D; ++d) {
          double acc = 0;
          for (int64_t j = 0; j < Lk; ++j) acc += s[j] / sum * v[(b * Lk + j) * kvs + g * D + d];
          out[((b * Lq + i) * H + h) * D + d] = acc;
        }
      }
    }
  return out;
}

TEST_P(BackendOps, Attention) {
  struct Case {
    const char* what;
    int64_t B, Lq, Lk, H, KvH, D;
    bool masked;
  };
  const Case cases[] = {{"smolvla prefix (GQA 15/5)", 2, 19, 19, 15, 5, 64, true},
                        {"smolvla expert joint", 2, 10, 29, 15, 5, 64, true},
                        {"pi0 gemma (MQA, head_dim 256)", 1, 12, 30, 8, 1, 256, true},
                        {"siglip (no mask)", 2, 16, 16, 12, 12, 64, false}};
  for (const Case& c : cases) {
    const int64_t qs = c.H * c.D + 3, kvs = c.KvH * c.D + 5;  // strided rows, as fused q|k|v buffers are
    const auto q = random_vec(c.B * c.Lq * qs, 20), k = random_vec(c.B * c.Lk * kvs, 21), v = random_vec(c.B * c.Lk * kvs, 22);
    std::vector<uint8_t> mask(std::size_t(c.B * c.Lq * c.Lk), 1);
    std::mt19937 gen(23);
    for (auto& m : mask) m = gen() % 4 != 0;
    for (int64_t j = 0; j < c.Lk; ++j) mask[j] = 0;  // one fully masked row: uniform weights
    const Array<float> qa = put(q), ka = put(k), va = put(v), out = be->alloc<float>(c.B * c.Lq * c.H * c.D);
    const Array<uint8_t> ma = put(mask);
    const double scale = 1.0 / std::sqrt(double(c.D));
    const double before = be->flops().attention;
    be->attention(qa.at(), qs, ka.at(), va.at(), kvs, c.masked ? Ptr<const uint8_t>(ma.at()) : Ptr<const uint8_t>(),
                  c.B, c.Lq, c.Lk, c.H, c.KvH, c.D, float(scale), out.at());
    EXPECT_DOUBLE_EQ(be->flops().attention - before, 4.0 * double(c.B * c.H * c.Lq * c.Lk * c.D));
    const auto want = reference_attention(q, qs, k, v, kvs, c.masked ? &mask : nullptr, c.B, c.Lq, c.Lk, c.H, c.KvH,
                                          c.D, scale);
    EXPECT_LT(rel_diff(label(std::string("attention ") + c.what), get(out), want), 1e-5);
  }
}

TEST_P(BackendOps, Rope) {
  for (const auto& [H, D] : {std::pair<int64_t, int64_t>{15, 64}, {1, 256}}) {
    const int64_t B = 2, L = 9;
    const auto x = random_vec(B * L * H * D, 30);
    std::vector<int64_t> pos(static_cast<std::size_t>(B * L));
    for (int64_t i = 0; i < B * L; ++i) pos[i] = (i * 7) % 300;
    const Array<float> xa = put(x);
    const Array<int64_t> pa = put(pos);
    be->rope(xa.at(), B, L, H, D, pa.at(), 10000.0f);
    std::vector<double> want(x.size());
    const int64_t half = D / 2;
    for (int64_t t = 0; t < B * L; ++t)
      for (int64_t h = 0; h < H; ++h)
        for (int64_t i = 0; i < half; ++i) {
          const double ts = std::pow(10000.0, 2.0 * double(i) / double(D));
          const double a = double(pos[t]) / ts;
          const double x1 = x[(t * H + h) * D + i], x2 = x[(t * H + h) * D + half + i];
          want[(t * H + h) * D + i] = x1 * std::cos(a) - x2 * std::sin(a);
          want[(t * H + h) * D + half + i] = x2 * std::cos(a) + x1 * std::sin(a);
        }
    EXPECT_LT(rel_diff(label("rope head_dim=" + std::to_string(D)), get(xa), want), 2e-5);
  }
}

// Rotation by angles the model computed itself (Qwen3-VL's multimodal and 2-D rotary): every head of a row shares them.
TEST_P(BackendOps, RopeRotate) {
  for (const auto& [H, D] : {std::pair<int64_t, int64_t>{16, 128}, {16, 64}, {2, 16}}) {
    const int64_t rows = 11, half = D / 2;
    const auto x = random_vec(rows * H * D, 31), angle = random_vec(rows * half, 32, -50, 50);
    std::vector<float> cs(angle.size()), sn(angle.size());
    for (std::size_t i = 0; i < angle.size(); ++i) cs[i] = std::cos(angle[i]), sn[i] = std::sin(angle[i]);
    const Array<float> xa = put(x), ca = put(cs), sa = put(sn);
    be->rope_rotate(xa.at(), rows, H, D, ca.at(), sa.at());
    std::vector<double> want(x.size());
    for (int64_t r = 0; r < rows; ++r)
      for (int64_t h = 0; h < H; ++h)
        for (int64_t i = 0; i < half; ++i) {
          const double c = cs[r * half + i], s = sn[r * half + i];
          const double x1 = x[(r * H + h) * D + i], x2 = x[(r * H + h) * D + half + i];
          want[(r * H + h) * D + i] = x1 * c - x2 * s;
          want[(r * H + h) * D + half + i] = x2 * c + x1 * s;
        }
    EXPECT_LT(rel_diff(label("rope_rotate head_dim=" + std::to_string(D)), get(xa), want), 1e-6);
  }
}

double gelu_tanh_ref(double v) { return 0.5 * v * (1 + std::tanh(std::sqrt(2 / M_PI) * (v + 0.044715 * v * v * v))); }
double silu_ref(double v) { return v / (1 + std::exp(-v)); }

TEST_P(BackendOps, Activations) {
  const int64_t rows = 5, n = 1024;
  const auto x = random_vec(rows * 2 * n, 40, -6, 6);
  for (Activation act : {Activation::silu, Activation::gelu_tanh}) {
    auto f = act == Activation::silu ? silu_ref : gelu_tanh_ref;
    const Array<float> xa = put(x), out = be->alloc<float>(rows * n);
    be->gated(xa.at(), rows, n, act, out.at());
    std::vector<double> want(static_cast<std::size_t>(rows * n));
    for (int64_t r = 0; r < rows; ++r)
      for (int64_t i = 0; i < n; ++i) want[r * n + i] = f(x[r * 2 * n + i]) * x[r * 2 * n + n + i];
    EXPECT_LT(rel_diff(label(std::string("gated ") + activation_name(act)), get(out), want), 1e-6);
    be->activate(xa.at(), rows * 2 * n, act);
    std::vector<double> want_act(x.size());
    for (std::size_t i = 0; i < x.size(); ++i) want_act[i] = f(x[i]);
    EXPECT_LT(rel_diff(label(std::string("activate ") + activation_name(act)), get(xa), want_act), 1e-6);
  }
  // The activations that have no gated form here (the Qwen3-VL mergers' exact GELU, the category MLPs' ReLU).
  for (Activation act : {Activation::gelu_erf, Activation::relu}) {
    const Array<float> xa = put(x);
    be->activate(xa.at(), int64_t(x.size()), act);
    std::vector<double> want(x.size());
    for (std::size_t i = 0; i < x.size(); ++i)
      want[i] = act == Activation::relu ? std::max(0.0, double(x[i])) : 0.5 * x[i] * (1 + std::erf(x[i] / std::sqrt(2.0)));
    EXPECT_LT(rel_diff(label(std::string("activate ") + activation_name(act)), get(xa), want), 1e-6);
    EXPECT_THROW(be->gated(xa.at(), 1, 4, act, xa.at()), Error) << activation_name(act);
  }
}

TEST_P(BackendOps, ElementwiseAndCopiesAreExact) {
  const int64_t rows = 6, n = 100;
  const auto a = random_vec(rows * n, 50), b = random_vec(rows * n, 51), g = random_vec(2 * n, 52);
  const Array<float> aa = put(a), ba = put(b), ga = put(g), out = be->alloc<float>(rows * n);
  be->add(aa.at(), ba.at(), rows * n, out.at());
  auto got = get(out);
  for (int64_t i = 0; i < rows * n; ++i) ASSERT_EQ(got[i], a[i] + b[i]);
  be->scale(out.at(), rows * n, 0.37f);
  got = get(out);
  for (int64_t i = 0; i < rows * n; ++i) ASSERT_EQ(got[i], (a[i] + b[i]) * 0.37f);
  be->axpy(out.at(), aa.at(), rows * n, -0.1f);
  const auto after = get(out);
  for (int64_t i = 0; i < rows * n; ++i) ASSERT_EQ(after[i], got[i] + -0.1f * a[i]);
  const Array<float> x = put(a);
  be->gated_add(x.at(), ba.at(), ga.at(), n, rows, n, 3);
  got = get(x);
  for (int64_t r = 0; r < rows; ++r)
    for (int64_t i = 0; i < n; ++i) ASSERT_EQ(got[r * n + i], a[r * n + i] + b[r * n + i] * g[(r / 3) * n + i]);
  // Strided copy, and a broadcast row (src stride 0).
  const Array<float> dst = put(std::vector<float>(std::size_t(rows * 130), 7.0f));
  be->copy_rows(aa.at(5), n, dst.at(2), 130, rows, 40);
  got = get(dst);
  for (int64_t r = 0; r < rows; ++r)
    for (int64_t i = 0; i < 130; ++i)
      ASSERT_EQ(got[r * 130 + i], i >= 2 && i < 42 ? a[r * n + 5 + i - 2] : 7.0f) << r << "," << i;
  be->copy_rows(ga.at(), 0, dst.at(), 130, rows, 100);
  got = get(dst);
  for (int64_t r = 0; r < rows; ++r)
    for (int64_t i = 0; i < 100; ++i) ASSERT_EQ(got[r * 130 + i], g[i]);
}

TEST_P(BackendOps, GatherRowsConvertsTheStoredDtype) {
  const int64_t rows = 50, width = 96;
  std::vector<uint16_t> bf16(static_cast<std::size_t>(rows * width));
  const auto values = random_vec(rows * width, 60);
  for (std::size_t i = 0; i < bf16.size(); ++i) {
    uint32_t bits;
    std::memcpy(&bits, &values[i], 4);
    bf16[i] = uint16_t(bits >> 16);
  }
  const Tensor host{DType::bf16, {rows, width}, bf16.data(), nullptr};
  auto table = be->table(host);
  EXPECT_EQ(table->rows(), rows);
  const std::vector<int64_t> ids = {3, 0, 49, 3};
  const Array<int64_t> ia = put(ids);
  const Array<float> out = be->alloc<float>(int64_t(ids.size()) * width);
  be->gather_rows(*table, ia.at(), int64_t(ids.size()), 2.5f, out.at());
  const auto got = get(out);
  for (std::size_t i = 0; i < ids.size(); ++i)
    for (int64_t j = 0; j < width; ++j) {
      const uint32_t bits = uint32_t(bf16[ids[i] * width + j]) << 16;
      float f;
      std::memcpy(&f, &bits, 4);
      ASSERT_EQ(got[i * width + j], f * 2.5f);
    }
  const Array<int64_t> bad = put(std::vector<int64_t>{rows});
  EXPECT_THROW(be->gather_rows(*table, bad.at(), 1, 1.0f, out.at()), Error);
}

TEST_P(BackendOps, PatchEmbedAndPixelShuffle) {
  // SigLIP-so400m's patch 14 over a 28x28 image, and SmolVLM's 16 over 32x32.
  for (const auto& [P, E] : {std::pair<int64_t, int64_t>{14, 24}, {16, 20}}) {
    const int64_t B = 2, C = 3, Hh = 2 * P, W = 2 * P;
    const auto px = random_vec(B * C * Hh * W, 70), w = random_vec(E * C * P * P, 71), bias = random_vec(E, 72);
    const Array<float> pa = put(px), wa = put(w), ba = put(bias), out = be->alloc<float>(B * 4 * E);
    be->patch_embed(pa.at(), B, C, Hh, W, wa.at(), ba.at(), E, P, out.at());
    std::vector<double> want(static_cast<std::size_t>(B * 4 * E));
    for (int64_t b = 0; b < B; ++b)
      for (int64_t py = 0; py < 2; ++py)
        for (int64_t pxx = 0; pxx < 2; ++pxx)
          for (int64_t e = 0; e < E; ++e) {
            double acc = bias[e];
            for (int64_t c = 0; c < C; ++c)
              for (int64_t i = 0; i < P; ++i)
                for (int64_t j = 0; j < P; ++j)
                  acc += double(px[((b * C + c) * Hh + py * P + i) * W + pxx * P + j]) * w[((e * C + c) * P + i) * P + j];
            want[((b * 4) + py * 2 + pxx) * E + e] = acc;
          }
    EXPECT_LT(rel_diff(label("patch_embed patch=" + std::to_string(P)), get(out), want), 1e-5);
  }
  // Pixel shuffle, ratio 2 over a 4x4 grid: out token (i, j) holds the 2x2 block's features in upstream order.
  const int64_t B = 1, S = 16, E = 3, r = 2;
  const auto x = random_vec(B * S * E, 73);
  const Array<float> xa = put(x), out = be->alloc<float>(B * S * E);
  be->pixel_shuffle(xa.at(), B, S, E, r, out.at());
  const auto got = get(out);
  // Upstream: view [side, side/r, E*r] -> permute -> [side/r, side/r, E*r*r] with the row pair innermost-but-one.
  const int64_t side = 4, h = side / r;
  for (int64_t i = 0; i < h; ++i)
    for (int64_t j = 0; j < h; ++j)
      for (int64_t a = 0; a < r; ++a)       // row offset in the block
        for (int64_t bb = 0; bb < r; ++bb)  // column offset
          for (int64_t e = 0; e < E; ++e) {
            const float want = x[((i * r + a) * side + j * r + bb) * E + e];
            ASSERT_EQ(got[(i * h + j) * E * r * r + (a * r + bb) * E + e], want) << i << j << a << bb << e;
          }
}

TEST_P(BackendOps, TimeEmbedding) {
  for (int64_t dim : {int64_t(720), int64_t(1024)}) {
    const Array<float> out = be->alloc<float>(dim);
    be->time_embedding(0.7, dim, 4e-3, 4.0, out.at());
    std::vector<double> want(static_cast<std::size_t>(dim));
    const int64_t half = dim / 2;
    for (int64_t i = 0; i < half; ++i) {
      const double frac = double(i) / double(half - 1);
      const double period = 4e-3 * std::pow(4.0 / 4e-3, frac);
      want[i] = std::sin(2 * M_PI * 0.7 / period);
      want[half + i] = std::cos(2 * M_PI * 0.7 / period);
    }
    EXPECT_LT(rel_diff(label("time_embedding dim=" + std::to_string(dim)), get(out), want), 1e-6);
  }
}

TEST_P(BackendOps, SamplerStep) {
  const int64_t chunk = 50, width = 32, action_dim = 6;
  const auto x = random_vec(chunk * width, 80), v = random_vec(chunk * width, 81), t = random_vec(chunk * width, 82);
  const auto w = random_vec(chunk, 83, 0, 1), prev = random_vec(chunk * width, 84);
  const Array<float> xa = put(x), va = put(v), ta = put(t), wa = put(w), pa = put(prev);
  const float time = 0.6f, gw = 3.5f;
  be->rtc_guide(xa.at(), va.at(), ta.at(), wa.at(), chunk, width, time, gw);
  const auto got = get(va);
  for (int64_t r = 0; r < chunk; ++r)
    for (int64_t a = 0; a < width; ++a) {
      const int64_t i = r * width + a;
      const float err = (t[i] - (x[i] - time * v[i])) * w[r];
      ASSERT_EQ(got[i], v[i] - gw * err);
    }
  const auto [diff, norm] = be->change_norms(va.at(), pa.at(), chunk, width, action_dim);
  double want_diff = 0, want_norm = 0;
  for (int64_t r = 0; r < chunk; ++r)
    for (int64_t a = 0; a < action_dim; ++a) {
      const int64_t i = r * width + a;
      want_diff += (double(got[i]) - prev[i]) * (double(got[i]) - prev[i]);
      want_norm += double(prev[i]) * prev[i];
    }
  EXPECT_NEAR(diff, want_diff, 1e-9 * want_diff);
  EXPECT_NEAR(norm, want_norm, 1e-9 * want_norm);
}

TEST_P(BackendOps, ConstantsReadAsUploaded) {
  const auto w = random_vec(64, 90);
  const Array<float> c = be->constant(w.data(), 64);
  EXPECT_EQ(get(c), w);
}

// Every operation on outputs poisoned with NaN, run twice: every output element is written (no NaN is left), and the
// two runs agree bit for bit (no race, no uninitialised read, no order that depends on scheduling). Shapes are the
// families' own, with the odd sizes that leave partial tiles and blocks.
TEST_P(BackendOps, EveryOpWritesItsWholeOutputTheSameTwice) {
  const float kPoison = std::numeric_limits<float>::quiet_NaN();
  struct Case {
    std::string name;
    int64_t out_size;
    std::function<void(Ptr<float> out)> run;  // re-uploads its inputs, then runs the op into out
  };
  const int64_t rows = 7, n = 960, B = 2, Lq = 19, Lk = 37, H = 15, KvH = 5, D = 64;
  const auto x = random_vec(rows * 2 * n, 100, -3, 3), w = random_vec(n, 101), mod = random_vec(2 * 3 * n, 102);
  const auto q = random_vec(B * Lq * H * D, 103), kv = random_vec(B * Lk * KvH * D, 104);
  std::vector<uint8_t> mask(std::size_t(B * Lq * Lk));
  for (std::size_t i = 0; i < mask.size(); ++i) mask[i] = (i * 7) % 5 != 0;
  std::vector<int64_t> pos(std::size_t(B * Lq));
  for (std::size_t i = 0; i < pos.size(); ++i) pos[i] = int64_t(i * 3);
  const Array<float> xa = put(x), wa = put(w), ma = put(mod), qa = put(q), ka = put(kv), va = put(random_vec(B * Lk * KvH * D, 105));
  const Array<uint8_t> mask_a = put(mask);
  const Array<int64_t> pos_a = put(pos);
  const auto lw = be->pack_linear(random_vec(320 * n, 106).data(), 320, n, random_vec(320, 107).data(), cpu::Precision::fp32);
  const std::vector<int64_t> ids = {5, 0, 49, 5, 17};
  const Array<int64_t> ids_a = put(ids);
  const auto table_values = random_vec(50 * 96, 108);
  const Tensor table_host{DType::f32, {50, 96}, table_values.data(), nullptr};
  const auto table = be->table(table_host);
  const auto pixels = random_vec(2 * 3 * 28 * 28, 109), patch_w = random_vec(24 * 3 * 14 * 14, 110);
  const Array<float> pixels_a = put(pixels), patch_wa = put(patch_w), patch_ba = put(random_vec(24, 111));
  auto copy_in = [&](Ptr<float> out, int64_t count) { be->upload(x.data(), count, out); };
  const std::vector<Case> cases = {
      {"linear", rows * 320, [&](Ptr<float> o) { be->linear(*lw, xa.at(), rows, o); }},
      {"layer_norm", rows * n, [&](Ptr<float> o) { be->layer_norm(xa.at(), rows, n, wa.at(), wa.at(), 1e-6f, o); }},
      {"rms_norm", rows * n, [&](Ptr<float> o) { be->rms_norm(xa.at(), rows, n, wa.at(), 1e-6f, o); }},
      {"rms_norm_modulated", rows * n,
       [&](Ptr<float> o) { be->rms_norm_modulated(xa.at(), rows, n, ma.at(), ma.at(n), 3 * n, 4, 1e-6f, o); }},
      {"modulate", rows * n, [&](Ptr<float> o) { copy_in(o, rows * n), be->modulate(o, rows, n, ma.at(), ma.at(n), 3 * n, 4); }},
      {"attention", B * Lq * H * D,
       [&](Ptr<float> o) { be->attention(qa.at(), H * D, ka.at(), va.at(), KvH * D, mask_a.at(), B, Lq, Lk, H, KvH, D, 0.125f, o); }},
      {"rope", B * Lq * H * D, [&](Ptr<float> o) { be->upload(q.data(), B * Lq * H * D, o), be->rope(o, B, Lq, H, D, pos_a.at(), 10000.0f); }},
      {"rope_rotate", rows * 2 * 64,
       [&](Ptr<float> o) { copy_in(o, rows * 2 * 64), be->rope_rotate(o, rows, 2, 64, wa.at(), wa.at(32)); }},
      {"activate gelu_tanh", rows * n, [&](Ptr<float> o) { copy_in(o, rows * n), be->activate(o, rows * n, Activation::gelu_tanh); }},
      {"activate silu", rows * n, [&](Ptr<float> o) { copy_in(o, rows * n), be->activate(o, rows * n, Activation::silu); }},
      {"gated silu", rows * n, [&](Ptr<float> o) { be->gated(xa.at(), rows, n, Activation::silu, o); }},
      {"add", rows * n, [&](Ptr<float> o) { be->add(xa.at(), xa.at(7), rows * n, o); }},
      {"scale", rows * n, [&](Ptr<float> o) { copy_in(o, rows * n), be->scale(o, rows * n, 0.3f); }},
      {"gated_add", rows * n, [&](Ptr<float> o) { copy_in(o, rows * n), be->gated_add(o, xa.at(3), ma.at(), n, rows, n, 4); }},
      {"copy_rows", rows * 130, [&](Ptr<float> o) { be->copy_rows(xa.at(), n, o, 130, rows, 130); }},
      {"gather_rows", int64_t(ids.size()) * 96, [&](Ptr<float> o) { be->gather_rows(*table, ids_a.at(), int64_t(ids.size()), 1.5f, o); }},
      {"patch_embed", 2 * 4 * 24,
       [&](Ptr<float> o) { be->patch_embed(pixels_a.at(), 2, 3, 28, 28, patch_wa.at(), patch_ba.at(), 24, 14, o); }},
      {"pixel_shuffle", 2 * 16 * 5, [&](Ptr<float> o) { be->pixel_shuffle(xa.at(), 2, 16, 5, 2, o); }},
      {"time_embedding", 720, [&](Ptr<float> o) { be->time_embedding(0.37, 720, 4e-3, 4.0, o); }},
      {"axpy", rows * n, [&](Ptr<float> o) { copy_in(o, rows * n), be->axpy(o, xa.at(1), rows * n, -0.4f); }},
      {"rtc_guide", 50 * 32,
       [&](Ptr<float> o) { copy_in(o, 50 * 32), be->rtc_guide(xa.at(), o, xa.at(5), wa.at(), 50, 32, 0.6f, 2.0f); }},
  };
  for (const Case& c : cases) {
    std::vector<float> runs[2];
    for (auto& result : runs) {
      const Array<float> out = put(std::vector<float>(std::size_t(c.out_size), kPoison));
      c.run(out.at());
      result = get(out);
    }
    int64_t unwritten = 0, differing = 0;
    for (int64_t i = 0; i < c.out_size; ++i) {
      unwritten += std::isnan(runs[0][i]);
      differing += std::memcmp(&runs[0][i], &runs[1][i], sizeof(float)) != 0;
    }
    EXPECT_EQ(unwritten, 0) << label(c.name) << ": output elements left unwritten (still the poison NaN)";
    EXPECT_EQ(differing, 0) << label(c.name) << ": two runs differ";
  }
}

// Every compiled backend (a CUDA build on a machine without a GPU skips "cuda" with one line), and the CUDA kernels'
// arithmetic run on the host, which every machine checks.
std::vector<std::string> backends_under_test() {
  std::vector<std::string> names = compiled_backends();
  names.push_back("cuda_math_on_host");
  return names;
}

INSTANTIATE_TEST_SUITE_P(EveryCompiledBackend, BackendOps, ::testing::ValuesIn(backends_under_test()),
                         [](const auto& info) { return info.param; });

TEST(BackendRegistry, UnknownBackendIsAClearError) {
  try {
    make_backend("tpu");
    FAIL() << "no error";
  } catch (const Error& e) {
    EXPECT_NE(std::string(e.what()).find("compiled: "), std::string::npos) << e.what();
  }
}

}  // namespace
}  // namespace tether::backend
