// See cuda_math_backend.h. Each loop names the kernel it mirrors (src/backend/cuda/*.cu).
#include "cuda_math_backend.h"

#include <cmath>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <new>
#include <vector>

#include "backend/cuda/element_math.h"
#include "core/dtype.h"
#include "core/error.h"

namespace tether::backend {
namespace {

namespace m = tether::cuda_math;

enum class Stored { f32, bf16, f16 };

float load(const void* data, Stored type, int64_t at) {
  if (type == Stored::bf16) return m::bf16_bits_to_float(static_cast<const uint16_t*>(data)[at]);
  if (type == Stored::f16) return m::f16_bits_to_float(static_cast<const uint16_t*>(data)[at]);
  return static_cast<const float*>(data)[at];
}

struct HostLinear final : LinearWeights {
  int64_t n = 0, k = 0;
  Stored type = Stored::f32;
  std::vector<uint16_t> half;
  std::vector<float> full, bias;
  int64_t out_features() const override { return n; }
  int64_t in_features() const override { return k; }
};

struct HostTable final : Table {
  int64_t row_count = 0, row_width = 0;
  Stored type = Stored::f32;
  std::vector<unsigned char> bytes;
  int64_t rows() const override { return row_count; }
  int64_t width() const override { return row_width; }
};

// block_sum's fixed tree over 256 partial sums, each a grid-stride sum: kernels.cu's row reductions.
constexpr int kThreads = 256;
template <typename Term>
double block_sum(int64_t n, Term term) {
  double partial[kThreads] = {};
  for (int t = 0; t < kThreads; ++t)
    for (int64_t i = t; i < n; i += kThreads) partial[t] += term(i);
  for (int width = kThreads / 2; width > 0; width /= 2)
    for (int t = 0; t < width; ++t) partial[t] += partial[t + width];
  return partial[0];
}

// The warp's butterfly (xor) reductions of attention.cu over 32 lanes.
template <typename Op>
void butterfly(float (&lanes)[32], Op op) {
  for (int offset = 16; offset > 0; offset /= 2) {
    float next[32];
    for (int l = 0; l < 32; ++l) next[l] = op(lanes[l], lanes[l ^ offset]);
    std::memcpy(lanes, next, sizeof next);
  }
}

class CudaMathOnHost final : public Backend {
 public:
  std::string name() const override { return "cuda_math_on_host"; }
  Device device() const override { return Device::cpu; }

  Array<float> constant(const float* data, int64_t n) override {
    Array<float> a = alloc<float>(n);
    if (n) std::memcpy(a.at().address(), data, std::size_t(n) * 4);
    return a;
  }
  void upload(const void* host, std::size_t bytes, Ptr<void> dst) override {
    if (bytes) std::memcpy(dst.address(), host, bytes);
  }
  void download(Ptr<const void> src, std::size_t bytes, void* host) override {
    if (bytes) std::memcpy(host, src.address(), bytes);
  }

  std::unique_ptr<LinearWeights> pack_linear(const float* weight, int64_t n, int64_t k, const float* bias,
                                             cpu::Precision precision) override {
    auto w = std::make_unique<HostLinear>();
    w->n = n, w->k = k;
    w->type = precision == cpu::Precision::bf16 ? Stored::bf16 : precision == cpu::Precision::fp16 ? Stored::f16 : Stored::f32;
    if (w->type == Stored::f32) {
      w->full.assign(weight, weight + n * k);
    } else {
      w->half.resize(std::size_t(n * k));
      for (int64_t i = 0; i < n * k; ++i)
        w->half[i] = w->type == Stored::bf16 ? m::float_to_bf16_bits(weight[i]) : f32_to_f16(weight[i]);
    }
    if (bias) w->bias.assign(bias, bias + n);
    return w;
  }
  std::unique_ptr<Table> table(const Tensor& host) override {
    auto t = std::make_unique<HostTable>();
    t->row_count = host.dim(0), t->row_width = host.dim(1);
    t->type = host.dtype == DType::bf16 ? Stored::bf16 : host.dtype == DType::f16 ? Stored::f16 : Stored::f32;
    if (host.dtype == DType::bf16 || host.dtype == DType::f16 || host.dtype == DType::f32) {
      t->bytes.assign(static_cast<const unsigned char*>(host.data), static_cast<const unsigned char*>(host.data) + host.nbytes());
    } else {
      t->bytes.resize(std::size_t(host.numel()) * 4);
      host.copy_f32(0, host.numel(), reinterpret_cast<float*>(t->bytes.data()));
    }
    return t;
  }

  // cuBLASLt's product (not a kernel of ours): fp32 accumulation over the operands as the device holds them, the
  // activations rounded by convert_kernel for the half types.
  void linear(const LinearWeights& weights, Ptr<const float> x, int64_t rows, Ptr<float> y, bool accumulate,
              int64_t ldy) override {
    const auto& w = static_cast<const HostLinear&>(weights);
    flops_.linear += 2.0 * double(rows) * double(w.n) * double(w.k);
    if (ldy == 0) ldy = w.n;
    for (int64_t r = 0; r < rows; ++r)
      for (int64_t j = 0; j < w.n; ++j) {
        float acc = 0;
        for (int64_t i = 0; i < w.k; ++i) {
          float xv = x.address()[r * w.k + i];
          if (w.type == Stored::bf16) xv = m::bf16_bits_to_float(m::float_to_bf16_bits(xv));
          if (w.type == Stored::f16) xv = m::f16_bits_to_float(f32_to_f16(xv));
          const float wv = w.type == Stored::f32 ? w.full[j * w.k + i] : load(w.half.data(), w.type, j * w.k + i);
          acc += xv * wv;
        }
        float& out = y.address()[r * ldy + j];
        out = (w.bias.empty() ? acc : acc + w.bias[j]) + (accumulate ? out : 0.0f);
      }
  }
  // layer_norm_kernel
  void layer_norm(Ptr<const float> x, int64_t rows, int64_t n, Ptr<const float> gamma, Ptr<const float> beta,
                  float eps, Ptr<float> y) override {
    for (int64_t r = 0; r < rows; ++r) {
      const float* xr = x.address() + r * n;
      const double mean = block_sum(n, [&](int64_t i) { return double(xr[i]); }) / double(n);
      const double squares = block_sum(n, [&](int64_t i) {
        const double d = double(xr[i]) - mean;
        return d * d;
      });
      const m::LayerNormStats stats = m::layer_norm_stats(mean, squares, n, eps);
      for (int64_t i = 0; i < n; ++i)
        y.address()[r * n + i] = m::layer_norm_apply(xr[i], stats, gamma.address(), beta.address(), i);
    }
  }
  // rms_norm_kernel
  void rms(Ptr<const float> x, int64_t rows, int64_t n, const float* weight, int kind, float eps, Ptr<float> y,
           const float* scale, const float* shift, int64_t mod_stride, int64_t rows_per_group) {
    for (int64_t r = 0; r < rows; ++r) {
      const float* xr = x.address() + r * n;
      const float inv = m::rms_inverse(block_sum(n, [&](int64_t i) { return double(xr[i]) * double(xr[i]); }), n, eps);
      const int64_t group = r / rows_per_group;
      for (int64_t i = 0; i < n; ++i) {
        float v = m::rms_apply(xr[i], inv, weight ? weight[i] : 0.0f, kind);
        if (scale) v = m::modulate(v, scale[group * mod_stride + i], shift[group * mod_stride + i]);
        y.address()[r * n + i] = v;
      }
    }
  }
  void rms_norm(Ptr<const float> x, int64_t rows, int64_t n, Ptr<const float> weight, float eps, Ptr<float> y,
                RmsScale kind) override {
    rms(x, rows, n, weight.address(), !weight ? 2 : kind == RmsScale::one_plus_weight ? 1 : 0, eps, y, nullptr,
        nullptr, 0, 1);
  }
  void rms_norm_modulated(Ptr<const float> x, int64_t rows, int64_t n, Ptr<const float> scale, Ptr<const float> shift,
                          int64_t mod_stride, int64_t rows_per_group, float eps, Ptr<float> y) override {
    if (rows_per_group < 1) throw Error(ErrorCode::invalid_argument, "rms_norm_modulated: rows_per_group must be >= 1");
    rms(x, rows, n, nullptr, 2, eps, y, scale.address(), shift.address(), mod_stride, rows_per_group);
  }
  // modulate_kernel
  void modulate(Ptr<float> y, int64_t rows, int64_t n, Ptr<const float> scale, Ptr<const float> shift,
                int64_t mod_stride, int64_t rows_per_group) override {
    for (int64_t e = 0; e < rows * n; ++e) {
      const int64_t g = (e / n / rows_per_group) * mod_stride, i = e % n;
      y.address()[e] = m::modulate(y.address()[e], scale.address()[g + i], shift.address()[g + i]);
    }
  }
  // attention_kernel: per query row, key tiles of 32 with the warp's max and sum reductions and the running softmax.
  void attention(Ptr<const float> q, int64_t q_stride, Ptr<const float> k, Ptr<const float> v, int64_t kv_stride,
                 Ptr<const uint8_t> mask, int64_t batch, int64_t len_q, int64_t len_k, int64_t heads, int64_t kv_heads,
                 int64_t head_dim, float scale, Ptr<float> out) override {
    flops_.attention += 4.0 * double(batch) * double(heads) * double(len_q) * double(len_k) * double(head_dim);
    const int64_t kv_head_of = heads / kv_heads;
    std::vector<float> acc(static_cast<std::size_t>(head_dim));
    for (int64_t b = 0; b < batch; ++b)
      for (int64_t h = 0; h < heads; ++h)
        for (int64_t row = 0; row < len_q; ++row) {
          const float* qr = q.address() + (b * len_q + row) * q_stride + h * head_dim;
          const int64_t kh = h / kv_head_of;
          m::OnlineSoftmax state = m::online_softmax_start();
          std::fill(acc.begin(), acc.end(), 0.0f);
          for (int64_t key0 = 0; key0 < len_k; key0 += 32) {
            float score[32], p[32];
            for (int lane = 0; lane < 32; ++lane) {
              const int64_t key = key0 + lane;
              if (key >= len_k) {
                score[lane] = -std::numeric_limits<float>::infinity();
                continue;
              }
              const float* kr = k.address() + (b * len_k + key) * kv_stride + kh * head_dim;
              float dot = 0;
              for (int64_t d = 0; d < head_dim; ++d) dot += qr[d] * kr[d];
              const bool keep = !mask || mask.address()[(b * len_q + row) * len_k + key];
              score[lane] = m::masked_score(dot, scale, keep);
            }
            float block_max[32];
            std::memcpy(block_max, score, sizeof score);
            butterfly(block_max, [](float a, float c) { return std::fmax(a, c); });
            const float factor = m::online_softmax_rescale(state, block_max[0]);
            for (int lane = 0; lane < 32; ++lane)
              p[lane] = key0 + lane < len_k ? m::online_softmax_weight(state, score[lane]) : 0.0f;
            float block_total[32];
            std::memcpy(block_total, p, sizeof p);
            butterfly(block_total, [](float a, float c) { return a + c; });
            state.sum += block_total[0];
            for (int64_t d = 0; d < head_dim; ++d) acc[d] *= factor;
            for (int j = 0; j < 32; ++j) {
              const int64_t key = std::min(key0 + j, len_k - 1);  // padding lanes carry a zero weight
              const float* vr = v.address() + (b * len_k + key) * kv_stride + kh * head_dim;
              for (int64_t d = 0; d < head_dim; ++d) acc[d] += p[j] * (key0 + j < len_k ? vr[d] : 0.0f);
            }
          }
          const float inv = 1.0f / state.sum;
          for (int64_t d = 0; d < head_dim; ++d)
            out.address()[(b * len_q + row) * heads * head_dim + h * head_dim + d] = acc[d] * inv;
        }
  }
  // rope_angles_kernel, then rope_rotate_kernel
  void rope(Ptr<float> x, int64_t batch, int64_t len, int64_t heads, int64_t head_dim, Ptr<const int64_t> positions,
            float max_wavelength, RopeAngles angles) override {
    const int64_t tokens = batch * len, half = head_dim / 2;
    std::vector<float> cs(std::size_t(tokens * half)), sn(cs.size());
    for (int64_t e = 0; e < tokens * half; ++e) {
      const float ts = m::rope_timescale(e % half, head_dim, max_wavelength, int(angles));
      const float radians = m::rope_angle(float(positions.address()[e / half]), ts, int(angles));
      cs[e] = std::cos(radians), sn[e] = std::sin(radians);
    }
    rotate(x.address(), tokens, heads, head_dim, cs.data(), sn.data());
  }
  void rope_rotate(Ptr<float> x, int64_t rows, int64_t heads, int64_t head_dim, Ptr<const float> cos,
                   Ptr<const float> sin) override {
    rotate(x.address(), rows, heads, head_dim, cos.address(), sin.address());
  }
  void activate(Ptr<float> x, int64_t n, Activation act) override {
    for (int64_t e = 0; e < n; ++e) x.address()[e] = m::activate(to_math(act), x.address()[e]);
  }
  void gated(Ptr<const float> gate_up, int64_t rows, int64_t n, Activation act, Ptr<float> out) override {
    if (act != Activation::silu && act != Activation::gelu_tanh)
      throw Error(ErrorCode::unsupported, std::string("gated: no gated form of ") + activation_name(act));
    for (int64_t e = 0; e < rows * n; ++e) {
      const float* row = gate_up.address() + (e / n) * 2 * n;
      out.address()[e] = m::gated(to_math(act), row[e % n], row[n + e % n]);
    }
  }
  void add(Ptr<const float> a, Ptr<const float> b, int64_t n, Ptr<float> out) override {
    for (int64_t e = 0; e < n; ++e) out.address()[e] = a.address()[e] + b.address()[e];
  }
  void scale(Ptr<float> x, int64_t n, float s) override {
    for (int64_t e = 0; e < n; ++e) x.address()[e] = x.address()[e] * s;
  }
  void gated_add(Ptr<float> x, Ptr<const float> y, Ptr<const float> gate, int64_t gate_stride, int64_t rows, int64_t n,
                 int64_t rows_per_group) override {
    for (int64_t e = 0; e < rows * n; ++e)
      x.address()[e] = x.address()[e] + y.address()[e] * gate.address()[(e / n / rows_per_group) * gate_stride + e % n];
  }
  void copy_rows(Ptr<const float> src, int64_t src_stride, Ptr<float> dst, int64_t dst_stride, int64_t rows,
                 int64_t width) override {
    for (int64_t e = 0; e < rows * width; ++e)
      dst.address()[(e / width) * dst_stride + e % width] = src.address()[(e / width) * src_stride + e % width];
  }
  void gather_rows(const Table& table, Ptr<const int64_t> ids, int64_t count, float scale, Ptr<float> out,
                   int64_t ldo) override {
    const auto& t = static_cast<const HostTable&>(table);
    if (ldo == 0) ldo = t.row_width;
    for (int64_t i = 0; i < count; ++i)
      if (ids.address()[i] < 0 || ids.address()[i] >= t.row_count)
        throw Error(ErrorCode::internal, "gather_rows: id outside the table");
    for (int64_t e = 0; e < count * t.row_width; ++e) {
      const int64_t r = e / t.row_width, i = e % t.row_width;
      const float v = load(t.bytes.data(), t.type, ids.address()[r] * t.row_width + i);
      out.address()[r * ldo + i] = scale == 1.0f ? v : v * scale;
    }
  }
  // im2col_kernel, then the product as linear() runs it
  void patch_embed(Ptr<const float> pixels, int64_t batch, int64_t channels, int64_t height, int64_t width,
                   Ptr<const float> weight, Ptr<const float> bias, int64_t embed, int64_t patch,
                   Ptr<float> out) override {
    const int64_t pw = width / patch, patches = (height / patch) * pw, col_len = channels * patch * patch;
    flops_.linear += 2.0 * double(batch * patches) * double(embed) * double(col_len);
    std::vector<float> cols(std::size_t(batch * patches * col_len));
    for (int64_t e = 0; e < int64_t(cols.size()); ++e) {
      const int64_t b = e / (patches * col_len), p = (e / col_len) % patches, j = e % col_len;
      const int64_t c = j / (patch * patch), ky = (j / patch) % patch, kx = j % patch;
      cols[e] = pixels.address()[((b * channels + c) * height + (p / pw) * patch + ky) * width + (p % pw) * patch + kx];
    }
    for (int64_t r = 0; r < batch * patches; ++r)
      for (int64_t o = 0; o < embed; ++o) {
        float acc = 0;
        for (int64_t j = 0; j < col_len; ++j) acc += cols[r * col_len + j] * weight.address()[o * col_len + j];
        out.address()[r * embed + o] = bias ? acc + bias.address()[o] : acc;
      }
  }
  // pixel_shuffle_kernel
  void pixel_shuffle(Ptr<const float> x, int64_t batch, int64_t seq, int64_t embed, int64_t ratio,
                     Ptr<float> out) override {
    int64_t side = 0;
    while ((side + 1) * (side + 1) <= seq) ++side;
    const int64_t out_side = side / ratio, out_seq = out_side * out_side, out_embed = embed * ratio * ratio;
    for (int64_t e = 0; e < batch * out_seq * out_embed; ++e) {
      const int64_t t = e / out_embed, f = e % out_embed;
      const int64_t b = t / out_seq, i2 = (t % out_seq) / out_side, j2 = t % out_side;
      const int64_t a = f / (ratio * embed), c = (f / embed) % ratio, d = f % embed;
      out.address()[e] = x.address()[(b * seq + (i2 * ratio + a) * side + (j2 * ratio + c)) * embed + d];
    }
  }
  void time_embedding(double time, int64_t dim, double min_period, double max_period, Ptr<float> out) override {
    const int64_t half = dim / 2;
    for (int64_t i = 0; i < half; ++i)
      m::time_embedding_pair(time, i, half, min_period, max_period, out.address()[i], out.address()[half + i]);
  }
  void axpy(Ptr<float> x, Ptr<const float> v, int64_t n, float a) override {
    for (int64_t e = 0; e < n; ++e) x.address()[e] = m::axpy(x.address()[e], a, v.address()[e]);
  }
  void rtc_guide(Ptr<const float> x, Ptr<float> v, Ptr<const float> target, Ptr<const float> weights, int64_t chunk,
                 int64_t width, float time, float guidance_weight) override {
    for (int64_t e = 0; e < chunk * width; ++e)
      v.address()[e] = m::rtc_guide(x.address()[e], v.address()[e], target.address()[e], weights.address()[e / width],
                                    time, guidance_weight);
  }
  // change_norms_kernel
  std::pair<double, double> change_norms(Ptr<const float> v, Ptr<const float> prev, int64_t chunk, int64_t width,
                                         int64_t action_dim) override {
    auto at = [&](int64_t e) { return (e / action_dim) * width + e % action_dim; };
    const double diff = block_sum(chunk * action_dim, [&](int64_t e) {
      const double d = double(v.address()[at(e)]) - double(prev.address()[at(e)]);
      return d * d;
    });
    const double norm = block_sum(chunk * action_dim, [&](int64_t e) {
      return double(prev.address()[at(e)]) * double(prev.address()[at(e)]);
    });
    return {diff, norm};
  }

 protected:
  std::shared_ptr<void> allocate_bytes(std::size_t bytes) override {
    void* p = std::aligned_alloc(256, (bytes + 255) / 256 * 256);
    if (!p) throw std::bad_alloc();
    return std::shared_ptr<void>(p, [](void* q) { std::free(q); });
  }

 private:
  static m::Act to_math(Activation a) {
    switch (a) {
      case Activation::silu: return m::Act::silu;
      case Activation::gelu_tanh: return m::Act::gelu_tanh;
      case Activation::gelu_erf: return m::Act::gelu_erf;
      case Activation::relu: return m::Act::relu;
    }
    return m::Act::silu;
  }
  // rope_rotate_kernel
  static void rotate(float* x, int64_t rows, int64_t heads, int64_t head_dim, const float* cs, const float* sn) {
    const int64_t half = head_dim / 2;
    for (int64_t e = 0; e < rows * heads * half; ++e) {
      const int64_t i = e % half, r = e / (half * heads);
      float* pair = x + (e / half) * head_dim + i;
      m::rotate_pair(pair[0], pair[half], cs[r * half + i], sn[r * half + i]);
    }
  }
};

}  // namespace

std::shared_ptr<Backend> make_cuda_math_on_host_backend() { return std::make_shared<CudaMathOnHost>(); }

}  // namespace tether::backend
