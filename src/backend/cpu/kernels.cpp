// Float32 vector kernels (norms, RoPE, activations, patch embedding, pixel shuffle).
// Built with -ffp-contract=off (see CMakeLists) so each multiply and add rounds separately, as in PyTorch.
#include "backend/cpu/kernels.h"

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <string>
#include <vector>

#include "backend/cpu/panel_gemm.h"
#include "backend/float_math.h"
#include "core/dtype.h"
#include "core/error.h"

namespace tether::cpu {
namespace {

// Below this many elements an OpenMP fork costs more than it saves.
constexpr int64_t kParallelMin = 1 << 15;

// The activations built on the polynomial exp and tanh of float_math.h are compiled twice, for the build's baseline
// (x86-64-v3: AVX2, 8 lanes) and for AVX-512 (16 lanes), and chosen under the TETHER_MAX_CPU_ISA cap as the panel
// GEMM is: GeGLU's tanh ran at half its AVX-512 speed. Each `<name>_span` is written once and inlined into each
// variant; every lane computes the same float32 steps (no contraction, see CMakeLists), so the variants give
// bit-identical results.
#if defined(__x86_64__)
#if defined(__clang__)  // clang takes no vector-width preference in the attribute
#define TETHER_AVX512_TARGET "avx512f,avx512dq,avx512bw,avx512vl"
#else  // GCC would otherwise keep 256-bit vectors
#define TETHER_AVX512_TARGET "avx512f,avx512dq,avx512bw,avx512vl,prefer-vector-width=512"
#endif
#define TETHER_ISA_VARIANTS(name, params, args)                                              \
  void name##_baseline params { name##_span args; }                                           \
  __attribute__((target(TETHER_AVX512_TARGET))) void name##_avx512 params { name##_span args; } \
  void name##_best params {                                                                                        \
    static const bool avx512 = cpu_paths().effective >= CpuIsa::avx512;                                            \
    if (avx512) return name##_avx512 args;                                                                         \
    name##_baseline args;                                                                                          \
  }
#else
#define TETHER_ISA_VARIANTS(name, params, args) \
  void name##_best params { name##_span args; }
#endif

// sqrt(2/pi) and the cubic coefficient of GELU's tanh approximation, as float32 constants.
constexpr float kGeluBeta = float(0.79788456080286535588);
constexpr float kGeluKappa = 0.044715f;

// The same float32 steps as PyTorch's formula; only tanh itself may differ by an ulp.
[[gnu::always_inline]] inline float gelu_tanh_one(float v) {
  const float cube = v * v * v;
  const float inner = kGeluBeta * (v + kGeluKappa * cube);
  return 0.5f * v * (1.0f + float_math::tanh_f32(inner));
}

[[gnu::always_inline]] inline void gelu_tanh_span(float* x, int64_t begin, int64_t end) {
#pragma omp simd
  for (int64_t i = begin; i < end; ++i) x[i] = gelu_tanh_one(x[i]);
}
// gelu(gate) is rounded to float32 before the product, as upstream's separate tensors are.
[[gnu::always_inline]] inline void gelu_tanh_mul_span(const float* gate, const float* up, float* out, int64_t begin,
                                                      int64_t end) {
#pragma omp simd
  for (int64_t i = begin; i < end; ++i) out[i] = gelu_tanh_one(gate[i]) * up[i];
}
[[gnu::always_inline]] inline void silu_span(float* x, int64_t begin, int64_t end) {
#pragma omp simd
  for (int64_t i = begin; i < end; ++i) x[i] = x[i] / (1.0f + float_math::exp_f32(-x[i]));
}
[[gnu::always_inline]] inline void silu_mul_span(const float* gate, const float* up, float* out, int64_t begin,
                                                 int64_t end) {
#pragma omp simd
  for (int64_t i = begin; i < end; ++i) {
    const float g = gate[i];
    out[i] = (g / (1.0f + float_math::exp_f32(-g))) * up[i];
  }
}
[[gnu::always_inline]] inline void exp_minus_span(float* x, float shift, int64_t n) {
#pragma omp simd
  for (int64_t i = 0; i < n; ++i) x[i] = float_math::exp_f32(x[i] - shift);
}

TETHER_ISA_VARIANTS(gelu_tanh, (float* x, int64_t begin, int64_t end), (x, begin, end))
TETHER_ISA_VARIANTS(gelu_tanh_mul, (const float* gate, const float* up, float* out, int64_t begin, int64_t end),
                    (gate, up, out, begin, end))
TETHER_ISA_VARIANTS(silu, (float* x, int64_t begin, int64_t end), (x, begin, end))
TETHER_ISA_VARIANTS(silu_mul, (const float* gate, const float* up, float* out, int64_t begin, int64_t end),
                    (gate, up, out, begin, end))
TETHER_ISA_VARIANTS(exp_minus, (float* x, float shift, int64_t n), (x, shift, n))

// Runs body(begin, end) over [0, n) split into one contiguous, 16-aligned chunk per thread. The simd
// loops stay in plain functions: GCC does not vectorise them inside `parallel for simd` outlining.
template <typename Body>
void for_chunks(int64_t n, Body&& body) {
  if (n < kParallelMin || omp_in_parallel()) {
    body(int64_t(0), n);
    return;
  }
#pragma omp parallel
  {
    const int64_t threads = omp_get_num_threads();
    const int64_t per = ((n + threads - 1) / threads + 15) / 16 * 16;
    const int64_t begin = std::min(n, per * omp_get_thread_num());
    const int64_t end = std::min(n, begin + per);
    if (begin < end) body(begin, end);
  }
}

// `what` is a message or a function building one: messages are built only on failure, because kernels run
// inside the denoise loop, which must not allocate.
template <typename What>
void require(bool ok, const char* kernel, What&& what) {
  if (ok) return;
  if constexpr (std::is_invocable_v<What>) {
    throw Error(ErrorCode::invalid_argument, std::string(kernel) + ": " + std::string(what()));
  } else {
    throw Error(ErrorCode::invalid_argument, std::string(kernel) + ": " + std::string(what));
  }
}

}  // namespace

void layer_norm(const float* x, int64_t rows, int64_t n, const float* gamma, const float* beta, float eps,
                float* y) {
  require(n > 0, "layer_norm", "row length must be positive");
#pragma omp parallel for schedule(static) if (rows * n >= kParallelMin)
  for (int64_t r = 0; r < rows; ++r) {
    const float* xr = x + r * n;
    float* yr = y + r * n;
    // Moments in double: PyTorch's float Welford pass is close to exact, plain float sums are not.
    double sum = 0.0;
#pragma omp simd reduction(+ : sum)
    for (int64_t i = 0; i < n; ++i) sum += xr[i];
    const double mean = sum / double(n);
    double sq = 0.0;
#pragma omp simd reduction(+ : sq)
    for (int64_t i = 0; i < n; ++i) {
      const double d = double(xr[i]) - mean;
      sq += d * d;
    }
    const float mean_f = float(mean);
    const float rstd = 1.0f / std::sqrt(float(sq / double(n)) + eps);
    const float shift = -rstd * mean_f;
    // Same association as PyTorch's CPU layer norm: (x * rstd + (-rstd * mean)) * gamma + beta.
#pragma omp simd
    for (int64_t i = 0; i < n; ++i) {
      float v = xr[i] * rstd + shift;
      if (gamma) v = v * gamma[i];
      if (beta) v = v + beta[i];
      yr[i] = v;
    }
  }
}

void rms_norm(const float* x, int64_t rows, int64_t n, const float* weight, float eps, float* y, bool one_plus) {
  require(n > 0, "rms_norm", "row length must be positive");
#pragma omp parallel for schedule(static) if (rows * n >= kParallelMin)
  for (int64_t r = 0; r < rows; ++r) {
    const float* xr = x + r * n;
    float* yr = y + r * n;
    double sq = 0.0;
#pragma omp simd reduction(+ : sq)
    for (int64_t i = 0; i < n; ++i) sq += double(xr[i]) * double(xr[i]);
    // The variance is a float32 tensor upstream; rsqrt is 1 / sqrt, each rounded.
    const float var = float(sq / double(n));
    const float inv = 1.0f / std::sqrt(var + eps);
    if (weight && one_plus) {
#pragma omp simd
      for (int64_t i = 0; i < n; ++i) yr[i] = (xr[i] * inv) * (1.0f + weight[i]);
    } else if (weight) {
#pragma omp simd
      for (int64_t i = 0; i < n; ++i) yr[i] = weight[i] * (xr[i] * inv);
    } else {
#pragma omp simd
      for (int64_t i = 0; i < n; ++i) yr[i] = xr[i] * inv;
    }
  }
}

// One token's heads rotated in place, split halves: x1' = x1 cos - x2 sin, x2' = x2 cos + x1 sin.
inline void rotate_heads(float* x, int64_t heads, int64_t head_dim, const float* cs, const float* sn) {
  const int64_t half = head_dim / 2;
  for (int64_t h = 0; h < heads; ++h) {
    float* x1 = x + h * head_dim;
    float* x2 = x1 + half;
#pragma omp simd
    for (int64_t i = 0; i < half; ++i) {
      const float a = x1[i];
      const float b = x2[i];
      x1[i] = a * cs[i] - b * sn[i];
      x2[i] = b * cs[i] + a * sn[i];
    }
  }
}

void rope_rotate(float* x, int64_t rows, int64_t heads, int64_t head_dim, const float* cos, const float* sin) {
  require(head_dim > 0 && head_dim % 2 == 0, "rope_rotate", [&] { return "head_dim must be even, got " + std::to_string(head_dim); });
  const int64_t half = head_dim / 2;
#pragma omp parallel for schedule(static) if (rows * heads * head_dim >= kParallelMin)
  for (int64_t r = 0; r < rows; ++r) {
    const float* cs = cos + r * half;
    const float* sn = sin + r * half;
    rotate_heads(x + r * heads * head_dim, heads, head_dim, cs, sn);
  }
}

void rope(float* x, int64_t batch, int64_t len, int64_t heads, int64_t head_dim, const int64_t* positions,
          float max_wavelength, RopeAngles angles) {
  const bool inverse_frequency = angles != RopeAngles::timescale_division;
  require(head_dim > 0 && head_dim % 2 == 0, "rope", [&] { return "head_dim must be even, got " + std::to_string(head_dim); });
  const int64_t half = head_dim / 2;
  // timescale[i] = max_wavelength ** (float(2 / D) * i), a float32 power; computing it in double and
  // rounding once gives the correctly rounded float.
  thread_local std::vector<float> timescale;
  timescale.resize(std::size_t(half));
  const float step = float(2.0 / double(head_dim));
  for (int64_t i = 0; i < half; ++i) {
    // transformers: arange(0, D, 2) / D in float32, base ** that, then 1.0 / it, all float32 (stored here as the
    // inverse frequency; the angle multiplies by it).
    const float exponent = inverse_frequency ? float(2 * i) / float(head_dim) : step * float(i);
    const float power = float(std::pow(double(max_wavelength), double(exponent)));
    timescale[std::size_t(i)] = inverse_frequency ? 1.0f / power : power;
    if (angles == RopeAngles::inverse_frequency_bf16) timescale[std::size_t(i)] = bf16_to_f32(f32_to_bf16(1.0f / power));
  }
  const float* ts = timescale.data();
  const int64_t tokens = batch * len;
#pragma omp parallel if (tokens * heads * head_dim >= kParallelMin)
  {
    thread_local std::vector<float> sin_cos;
    sin_cos.resize(std::size_t(2 * half));
    float* sn = sin_cos.data();
    float* cs = sn + half;
#pragma omp for schedule(static)
    for (int64_t t = 0; t < tokens; ++t) {
      const float pos = float(positions[t]);
      for (int64_t i = 0; i < half; ++i) {
        const float radians = inverse_frequency ? pos * ts[i] : pos / ts[i];
        sn[i] = std::sin(radians);
        cs[i] = std::cos(radians);
      }
      rotate_heads(x + t * heads * head_dim, heads, head_dim, cs, sn);
    }
  }
}

void softmax_rows(float* x, int64_t rows, int64_t n) {
  if (n <= 0) return;
#pragma omp parallel for schedule(static) if (rows * n >= kParallelMin)
  for (int64_t r = 0; r < rows; ++r) softmax_row(x + r * n, n);
}

float lane_sum(const float* x, int64_t n) {
  float lanes[8] = {};
  int64_t i = 0;
  for (; i + 8 <= n; i += 8)
    for (int l = 0; l < 8; ++l) lanes[l] += x[i + l];
  for (int l = 0; i + l < n; ++l) lanes[l] += x[i + l];
  return ((lanes[0] + lanes[1]) + (lanes[2] + lanes[3])) + ((lanes[4] + lanes[5]) + (lanes[6] + lanes[7]));
}

void softmax_row(float* x, int64_t n, const uint8_t* keep) {
  float mx = x[0];
#pragma omp simd reduction(max : mx)
  for (int64_t i = 0; i < n; ++i) mx = x[i] > mx ? x[i] : mx;
  exp_minus_best(x, mx, n);
  // Lanes follow each kept entry's rank among the kept ones, not its position: masked padding anywhere in the row
  // (masked entries are exact zeros here) leaves every lane's sum, and so the result, unchanged.
  float sum;
  if (keep) {
    thread_local std::vector<float> kept;
    if (kept.size() < std::size_t(n)) kept.resize(std::size_t(n));
    int64_t count = 0;
    for (int64_t i = 0; i < n; ++i)
      if (keep[i]) kept[std::size_t(count++)] = x[i];
    sum = count > 0 ? lane_sum(kept.data(), count) : lane_sum(x, n);
  } else {
    sum = lane_sum(x, n);
  }
  const float inv = 1.0f / sum;
#pragma omp simd
  for (int64_t i = 0; i < n; ++i) x[i] = x[i] * inv;
}

void gelu_tanh(float* x, int64_t n) {
  for_chunks(n, [x](int64_t begin, int64_t end) { gelu_tanh_best(x, begin, end); });
}

void gelu_tanh_mul(const float* gate, const float* up, int64_t n, float* out) {
  for_chunks(n, [=](int64_t begin, int64_t end) { gelu_tanh_mul_best(gate, up, out, begin, end); });
}

void silu(float* x, int64_t n) {
  for_chunks(n, [x](int64_t begin, int64_t end) { silu_best(x, begin, end); });
}

void gelu_erf(float* x, int64_t n) {
  constexpr float kInvSqrt2 = float(0.70710678118654752440);
  for_chunks(n, [x](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) x[i] = (x[i] * 0.5f) * (1.0f + std::erf(x[i] * kInvSqrt2));
  });
}

void relu(float* x, int64_t n) {
  for_chunks(n, [x](int64_t begin, int64_t end) {
#pragma omp simd
    for (int64_t i = begin; i < end; ++i) x[i] = x[i] < 0.0f ? 0.0f : x[i];
  });
}

void silu_mul(const float* gate, const float* up, int64_t n, float* out) {
  for_chunks(n, [=](int64_t begin, int64_t end) { silu_mul_best(gate, up, out, begin, end); });
}

void add(const float* a, const float* b, int64_t n, float* out) {
  for_chunks(n, [=](int64_t begin, int64_t end) {
#pragma omp simd
    for (int64_t i = begin; i < end; ++i) out[i] = a[i] + b[i];
  });
}

void scale(float* x, int64_t n, float s) {
  for_chunks(n, [=](int64_t begin, int64_t end) {
#pragma omp simd
    for (int64_t i = begin; i < end; ++i) x[i] = x[i] * s;
  });
}

void patch_embed(const float* pixels, int64_t batch, int64_t channels, int64_t height, int64_t width,
                 const float* weight, const float* bias, int64_t embed, int64_t patch, float* out) {
  require(patch > 0 && height % patch == 0 && width % patch == 0, "patch_embed",
          [&] {
            return "image " + std::to_string(height) + "x" + std::to_string(width) + " is not a multiple of patch " +
                   std::to_string(patch);
          });
  const int64_t ph = height / patch;
  const int64_t pw = width / patch;
  const int64_t patches = ph * pw;
  const int64_t col_len = channels * patch * patch;  // weight rows are [C, P, P] flattened
  // One image's im2col matrix, reused across calls (about 3 MB for a 512x512 SigLIP input).
  thread_local std::vector<float> cols;
  cols.resize(std::size_t(patches * col_len));
  float* col = cols.data();
  for (int64_t b = 0; b < batch; ++b) {
    const float* img = pixels + b * channels * height * width;
#pragma omp parallel for schedule(static) if (patches * col_len >= kParallelMin)
    for (int64_t p = 0; p < patches; ++p) {
      const int64_t py = p / pw;
      const int64_t px = p % pw;
      float* dst = col + p * col_len;
      for (int64_t c = 0; c < channels; ++c) {
        for (int64_t ky = 0; ky < patch; ++ky) {
          const float* src = img + (c * height + py * patch + ky) * width + px * patch;
          std::memcpy(dst, src, sizeof(float) * std::size_t(patch));
          dst += patch;
        }
      }
    }
    // The panel kernel's fixed-order chains, like every other product: the same bits on every CPU.
    detail::gemm_fixed_order(patches, embed, col_len, col, col_len, weight, col_len, /*trans_b=*/true,
                             out + b * patches * embed, embed, bias);
  }
}

void pixel_shuffle(const float* x, int64_t batch, int64_t seq, int64_t embed, int64_t ratio, float* out) {
  int64_t side = int64_t(std::llround(std::sqrt(double(seq))));
  require(side * side == seq, "pixel_shuffle", [&] { return "sequence length " + std::to_string(seq) + " is not a square"; });
  require(ratio > 0 && side % ratio == 0, "pixel_shuffle",
          [&] { return "side " + std::to_string(side) + " is not divisible by ratio " + std::to_string(ratio); });
  const int64_t out_side = side / ratio;
  const int64_t out_seq = out_side * out_side;
  const int64_t out_embed = embed * ratio * ratio;
  // Output token (i2, j2) holds, in order a = 0..r-1 then c = 0..r-1, the input token at grid position
  // (i2*r + a, j2*r + c): the view/permute/reshape chain upstream reduces to this copy.
#pragma omp parallel for schedule(static) if (batch * seq * embed >= kParallelMin)
  for (int64_t t = 0; t < batch * out_seq; ++t) {
    const int64_t b = t / out_seq;
    const int64_t i2 = (t % out_seq) / out_side;
    const int64_t j2 = t % out_side;
    float* dst = out + t * out_embed;
    for (int64_t a = 0; a < ratio; ++a) {
      for (int64_t c = 0; c < ratio; ++c) {
        const int64_t src_token = (i2 * ratio + a) * side + (j2 * ratio + c);
        std::memcpy(dst + (a * ratio + c) * embed, x + (b * seq + src_token) * embed,
                    sizeof(float) * std::size_t(embed));
      }
    }
  }
}

}  // namespace tether::cpu
