// The CPU backend: host memory, the packed linear layers (oneDNN or the panel GEMM) and the vector kernels.
#include "backend/cpu/cpu_backend.h"

#include <cmath>
#include <cstdlib>
#include <cstring>
#include <new>

#include "backend/cpu/kernels.h"
#include "backend/cpu/packed_linear.h"
#include "core/error.h"

namespace tether::backend {

namespace {

class CpuLinear final : public LinearWeights {
 public:
  cpu::PackedLinear packed;
  int64_t out_features() const override { return packed.n(); }
  int64_t in_features() const override { return packed.k(); }
};

class CpuTable final : public Table {
 public:
  explicit CpuTable(Tensor t) : host(std::move(t)) {}
  Tensor host;
  int64_t rows() const override { return host.dim(0); }
  int64_t width() const override { return host.dim(1); }
};

// 64-byte aligned heap storage, so vector loads of an activation never straddle a cache line.
std::shared_ptr<void> aligned_storage(std::size_t bytes) {
  const std::size_t rounded = (bytes + 63) / 64 * 64;
  void* p = std::aligned_alloc(64, rounded);
  if (!p) throw std::bad_alloc();
  return std::shared_ptr<void>(p, [](void* q) { std::free(q); });
}

class CpuBackend final : public Backend {
 public:
  std::string name() const override { return "cpu"; }
  Device device() const override { return Device::cpu; }

  Array<float> constant(const float* data, int64_t n) override {
    // Host memory already: a view, kept alive by the caller (the checkpoint mapping or the loader's copies).
    return Array<float>(nullptr, const_cast<float*>(data), n);
  }
  void upload(const void* host, std::size_t bytes, Ptr<void> dst) override {
    if (bytes) std::memmove(dst.address(), host, bytes);
  }
  void download(Ptr<const void> src, std::size_t bytes, void* host) override {
    if (bytes) std::memmove(host, src.address(), bytes);
  }

  std::unique_ptr<LinearWeights> pack_linear(const float* weight, int64_t n, int64_t k, const float* bias,
                                             cpu::Precision precision) override {
    auto w = std::make_unique<CpuLinear>();
    w->packed.pack(weight, n, k, bias, precision);
    return w;
  }
  std::unique_ptr<Table> table(const Tensor& host) override {
    if (host.shape.size() != 2) throw Error(ErrorCode::invalid_argument, "table: expected a 2-d tensor, got " + shape_str(host.shape));
    return std::make_unique<CpuTable>(host);
  }

  void linear(const LinearWeights& w, Ptr<const float> x, int64_t m, Ptr<float> y, bool accumulate,
              int64_t ldy) override {
    const auto& packed = static_cast<const CpuLinear&>(w).packed;
    flops_.linear += 2.0 * double(m) * double(packed.n()) * double(packed.k());
    packed.forward(x.address(), m, y.address(), accumulate, ldy);
  }
  void layer_norm(Ptr<const float> x, int64_t rows, int64_t n, Ptr<const float> gamma, Ptr<const float> beta,
                  float eps, Ptr<float> y) override {
    cpu::layer_norm(x.address(), rows, n, gamma.address(), beta.address(), eps, y.address());
  }
  void rms_norm(Ptr<const float> x, int64_t rows, int64_t n, Ptr<const float> weight, float eps, Ptr<float> y,
                RmsScale kind) override {
    cpu::rms_norm(x.address(), rows, n, weight.address(), eps, y.address(), kind == RmsScale::one_plus_weight);
  }
  void rms_norm_modulated(Ptr<const float> x, int64_t rows, int64_t n, Ptr<const float> scale, Ptr<const float> shift,
                          int64_t mod_stride, int64_t rows_per_group, float eps, Ptr<float> y) override {
    if (rows_per_group < 1) throw Error(ErrorCode::invalid_argument, "rms_norm_modulated: rows_per_group must be >= 1");
    cpu::rms_norm(x.address(), rows, n, nullptr, eps, y.address());
    modulate(y, rows, n, scale, shift, mod_stride, rows_per_group);
  }
  void attention(Ptr<const float> q, int64_t q_stride, Ptr<const float> k, Ptr<const float> v, int64_t kv_stride,
                 Ptr<const uint8_t> mask, int64_t batch, int64_t len_q, int64_t len_k, int64_t heads, int64_t kv_heads,
                 int64_t head_dim, float scale, Ptr<float> out) override {
    flops_.attention += 4.0 * double(batch) * double(heads) * double(len_q) * double(len_k) * double(head_dim);
    cpu::attention(q.address(), q_stride, k.address(), v.address(), kv_stride, mask.address(), batch, len_q, len_k,
                   heads, kv_heads, head_dim, scale, out.address());
  }
  void rope(Ptr<float> x, int64_t batch, int64_t len, int64_t heads, int64_t head_dim, Ptr<const int64_t> positions,
            float max_wavelength, backend::RopeAngles angles) override {
    const cpu::RopeAngles a = angles == backend::RopeAngles::timescale_division ? cpu::RopeAngles::timescale_division
                              : angles == backend::RopeAngles::inverse_frequency ? cpu::RopeAngles::inverse_frequency
                                                                                 : cpu::RopeAngles::inverse_frequency_bf16;
    cpu::rope(x.address(), batch, len, heads, head_dim, positions.address(), max_wavelength, a);
  }
  void modulate(Ptr<float> y, int64_t rows, int64_t n, Ptr<const float> scale, Ptr<const float> shift,
                int64_t mod_stride, int64_t rows_per_group) override {
    if (rows_per_group < 1) throw Error(ErrorCode::invalid_argument, "modulate: rows_per_group must be >= 1");
    float* out = y.address();
    const float *sc = scale.address(), *sh = shift.address();
    for (int64_t r = 0; r < rows; ++r) {
      const float* s = sc + (r / rows_per_group) * mod_stride;
      const float* t = sh + (r / rows_per_group) * mod_stride;
      float* yr = out + r * n;
#pragma omp simd
      for (int64_t i = 0; i < n; ++i) yr[i] = yr[i] * (1.0f + s[i]) + t[i];
    }
  }
  void rope_rotate(Ptr<float> x, int64_t rows, int64_t heads, int64_t head_dim, Ptr<const float> cos,
                   Ptr<const float> sin) override {
    cpu::rope_rotate(x.address(), rows, heads, head_dim, cos.address(), sin.address());
  }
  void activate(Ptr<float> x, int64_t n, Activation act) override {
    switch (act) {
      case Activation::silu: cpu::silu(x.address(), n); return;
      case Activation::gelu_tanh: cpu::gelu_tanh(x.address(), n); return;
      case Activation::gelu_erf: cpu::gelu_erf(x.address(), n); return;
      case Activation::relu: cpu::relu(x.address(), n); return;
    }
  }
  void gated(Ptr<const float> gate_up, int64_t rows, int64_t n, Activation act, Ptr<float> out) override {
    if (act != Activation::silu && act != Activation::gelu_tanh)
      throw Error(ErrorCode::unsupported, std::string("gated: no gated form of ") + backend::activation_name(act));
    const float* gu = gate_up.address();
    float* o = out.address();
    // Rows in parallel (each row's kernel then runs on its thread alone); one row splits its own elements.
#pragma omp parallel for schedule(static) if (rows > 1 && rows * n >= (1 << 15))
    for (int64_t r = 0; r < rows; ++r) {
      const float *gate = gu + r * 2 * n, *up = gate + n;
      if (act == Activation::silu) cpu::silu_mul(gate, up, n, o + r * n);
      else cpu::gelu_tanh_mul(gate, up, n, o + r * n);
    }
  }
  void add(Ptr<const float> a, Ptr<const float> b, int64_t n, Ptr<float> out) override {
    cpu::add(a.address(), b.address(), n, out.address());
  }
  void scale(Ptr<float> x, int64_t n, float s) override { cpu::scale(x.address(), n, s); }
  void gated_add(Ptr<float> x, Ptr<const float> y, Ptr<const float> gate, int64_t gate_stride, int64_t rows, int64_t n,
                 int64_t rows_per_group) override {
    if (rows_per_group < 1) throw Error(ErrorCode::invalid_argument, "gated_add: rows_per_group must be >= 1");
    float* xs = x.address();
    const float *ys = y.address(), *gs = gate.address();
    for (int64_t r = 0; r < rows; ++r) {
      const float* g = gs + (r / rows_per_group) * gate_stride;
#pragma omp simd
      for (int64_t i = 0; i < n; ++i) xs[r * n + i] = xs[r * n + i] + ys[r * n + i] * g[i];
    }
  }
  void copy_rows(Ptr<const float> src, int64_t src_stride, Ptr<float> dst, int64_t dst_stride, int64_t rows,
                 int64_t width) override {
    const float* s = src.address();
    float* d = dst.address();
    for (int64_t r = 0; r < rows; ++r) std::memcpy(d + r * dst_stride, s + r * src_stride, std::size_t(width) * sizeof(float));
  }
  void gather_rows(const Table& table, Ptr<const int64_t> ids, int64_t count, float scale, Ptr<float> out,
                   int64_t ldo) override {
    const Tensor& t = static_cast<const CpuTable&>(table).host;
    const int64_t width = t.dim(1);
    if (ldo == 0) ldo = width;
    const int64_t* id = ids.address();
    for (int64_t i = 0; i < count; ++i) {
      if (id[i] < 0 || id[i] >= t.dim(0))
        throw Error(ErrorCode::internal, "gather_rows: id " + std::to_string(id[i]) + " outside the table's " +
                                             std::to_string(t.dim(0)) + " rows");
      float* row = out.address() + i * ldo;
      t.copy_f32(id[i] * width, width, row);
      if (scale != 1.0f) cpu::scale(row, width, scale);
    }
  }
  void patch_embed(Ptr<const float> pixels, int64_t batch, int64_t channels, int64_t height, int64_t width,
                   Ptr<const float> weight, Ptr<const float> bias, int64_t embed, int64_t patch,
                   Ptr<float> out) override {
    flops_.linear += 2.0 * double(batch) * double((height / patch) * (width / patch)) * double(embed) *
                     double(channels * patch * patch);
    cpu::patch_embed(pixels.address(), batch, channels, height, width, weight.address(), bias.address(), embed, patch,
                     out.address());
  }
  void pixel_shuffle(Ptr<const float> x, int64_t batch, int64_t seq, int64_t embed, int64_t ratio,
                     Ptr<float> out) override {
    cpu::pixel_shuffle(x.address(), batch, seq, embed, ratio, out.address());
  }
  void time_embedding(double time, int64_t dim, double min_period, double max_period, Ptr<float> out) override {
    // The fractions follow torch.linspace, which fills the upper half counting back from the end.
    const int64_t half = dim / 2;
    const double step = half > 1 ? 1.0 / double(half - 1) : 0.0;
    float* o = out.address();
    for (int64_t i = 0; i < half; ++i) {
      const double fraction = i < half / 2 ? double(i) * step : 1.0 - double(half - 1 - i) * step;
      const double period = min_period * std::pow(max_period / min_period, fraction);
      const double angle = (1.0 / period) * 2.0 * M_PI * time;
      o[i] = float(std::sin(angle));
      o[half + i] = float(std::cos(angle));
    }
  }

  void axpy(Ptr<float> x, Ptr<const float> v, int64_t n, float a) override {
    float* xs = x.address();
    const float* vs = v.address();
#pragma omp simd
    for (int64_t i = 0; i < n; ++i) xs[i] += a * vs[i];
  }
  void rtc_guide(Ptr<const float> x, Ptr<float> v, Ptr<const float> target, Ptr<const float> weights, int64_t chunk,
                 int64_t width, float time, float guidance_weight) override {
    const float* xs = x.address();
    float* vs = v.address();
    const float *tg = target.address(), *ws = weights.address();
    for (int64_t r = 0; r < chunk; ++r) {
      for (int64_t a = 0; a < width; ++a) {
        const int64_t i = r * width + a;
        const float x1 = xs[i] - time * vs[i];
        const float err = (tg[i] - x1) * ws[r];
        vs[i] = vs[i] - guidance_weight * err;
      }
    }
  }
  std::pair<double, double> change_norms(Ptr<const float> v, Ptr<const float> prev, int64_t chunk, int64_t width,
                                         int64_t action_dim) override {
    const float *vs = v.address(), *ps = prev.address();
    double diff = 0, norm = 0;
    for (int64_t r = 0; r < chunk; ++r) {
      for (int64_t a = 0; a < action_dim; ++a) {
        const int64_t i = r * width + a;
        const double d = double(vs[i]) - double(ps[i]);
        diff += d * d;
        norm += double(ps[i]) * double(ps[i]);
      }
    }
    return {diff, norm};
  }

 protected:
  std::shared_ptr<void> allocate_bytes(std::size_t bytes) override { return aligned_storage(bytes); }
};

}  // namespace

std::shared_ptr<Backend> make_cpu_backend() { return std::make_shared<CpuBackend>(); }

}  // namespace tether::backend
