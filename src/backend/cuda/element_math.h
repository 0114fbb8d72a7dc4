// The per-element math of the CUDA kernels, written once for host and device: each kernel does its indexing and
// synchronisation and calls these for the arithmetic, and the host test (tests/backend/test_cuda_element_math.cpp)
// runs the very same functions against float64 references on machines without a GPU. Kernels that the op tests
// require to be bit-exact are built without FMA contraction (-fmad=false), as the host side is
// (-ffp-contract=off), so host and device round every step alike.
#pragma once

#include <cmath>
#include <cstdint>

#include "backend/float_math.h"

namespace tether::cuda_math {

using float_math::bits_to_float;
using float_math::exp_f32;
using float_math::float_to_bits;
using float_math::tanh_f32;

// bfloat16 storage to float32: the top half of the float's bits.
TETHER_HD float bf16_bits_to_float(uint16_t h) { return bits_to_float(uint32_t(h) << 16); }

// float32 to bfloat16, rounded to nearest even (NaN kept a quiet NaN), as torch's .to(torch.bfloat16).
TETHER_HD uint16_t float_to_bf16_bits(float f) {
  const uint32_t bits = float_to_bits(f);
  if ((bits & 0x7fffffffu) > 0x7f800000u) return uint16_t((bits >> 16) | 0x40u);
  const uint32_t rounding = 0x7fffu + ((bits >> 16) & 1u);
  return uint16_t((bits + rounding) >> 16);
}

// IEEE half storage to float32, exact for every half value (subnormals, infinities and NaN included).
TETHER_HD float f16_bits_to_float(uint16_t h) {
  const uint32_t sign = uint32_t(h & 0x8000u) << 16;
  const uint32_t exponent = (h >> 10) & 0x1fu;
  const uint32_t mantissa = h & 0x3ffu;
  if (exponent == 0x1fu) return bits_to_float(sign | 0x7f800000u | (mantissa << 13));
  if (exponent != 0) return bits_to_float(sign | ((exponent + 112u) << 23) | (mantissa << 13));
  // Subnormal: mantissa * 2^-24, exact in float32.
  const float magnitude = float(mantissa) * 5.9604644775390625e-8f;
  return sign ? -magnitude : magnitude;
}

// PyTorch's GELU(approximate="tanh"), each step rounded as its float32 formula is.
TETHER_HD float gelu_tanh(float v) {
  const float kBeta = 0.7978845608028654f;  // sqrt(2 / pi)
  const float kKappa = 0.044715f;
  const float cube = v * v * v;
  const float inner = kBeta * (v + kKappa * cube);
  return 0.5f * v * (1.0f + tanh_f32(inner));
}

TETHER_HD float silu(float v) { return v / (1.0f + exp_f32(-v)); }

TETHER_HD float relu(float v) { return v < 0.0f ? 0.0f : v; }

// The exact GELU, (x * 0.5) * (1 + erf(x / sqrt(2))), with the platform's erff (correctly rounded to within 2 ulp on
// both sides).
TETHER_HD float gelu_erf(float v) {
  const float kInvSqrt2 = 0.7071067811865476f;
  return (v * 0.5f) * (1.0f + erff(v * kInvSqrt2));
}

enum class Act : int { silu = 0, gelu_tanh = 1, gelu_erf = 2, relu = 3 };

TETHER_HD float activate(Act act, float v) {
  switch (act) {
    case Act::silu: return silu(v);
    case Act::gelu_tanh: return gelu_tanh(v);
    case Act::gelu_erf: return gelu_erf(v);
    case Act::relu: return relu(v);
  }
  return v;
}

// A gated unit's element: act(gate) rounded to float32, then times up (upstream's two separate tensors).
TETHER_HD float gated(Act act, float gate, float up) { return activate(act, gate) * up; }

// ---- norms: the row statistics are reduced by the kernel (in double); these turn them into the output.

// 1 / sqrt(var + eps) with var the float32-rounded mean of squares, as upstream's float32 tensors round it.
TETHER_HD float rms_inverse(double sum_squares, int64_t n, float eps) {
  const float var = float(sum_squares / double(n));
  return 1.0f / sqrtf(var + eps);
}

// Llama's weight * (x * inv), Gemma's (x * inv) * (1 + weight), or x * inv with no weight (kind 2).
TETHER_HD float rms_apply(float x, float inv, float weight, int kind) {
  if (kind == 0) return weight * (x * inv);
  if (kind == 1) return (x * inv) * (1.0f + weight);
  return x * inv;
}

struct LayerNormStats {
  float rstd, shift;  // y = x * rstd + shift, then * gamma + beta
};

// From the row's sum and centred sum of squares (both double): PyTorch's CPU association.
TETHER_HD LayerNormStats layer_norm_stats(double mean, double centred_squares, int64_t n, float eps) {
  const float mean_f = float(mean);
  const float rstd = 1.0f / sqrtf(float(centred_squares / double(n)) + eps);
  return {rstd, -rstd * mean_f};
}

TETHER_HD float layer_norm_apply(float x, LayerNormStats s, const float* gamma, const float* beta, int64_t i) {
  float v = x * s.rstd + s.shift;
  if (gamma) v = v * gamma[i];
  if (beta) v = v + beta[i];
  return v;
}

// An adaptive norm's modulation: y * (1 + scale) + shift.
TETHER_HD float modulate(float y, float scale, float shift) { return y * (1.0f + scale) + shift; }

// ---- rotary embedding

// The rotation of one split-halves pair: x1' = x1 cos - x2 sin, x2' = x2 cos + x1 sin.
TETHER_HD void rotate_pair(float& x1, float& x2, float c, float s) {
  const float a = x1, b = x2;
  x1 = a * c - b * s;
  x2 = b * c + a * s;
}

// Where a rotary pair's angle comes from (backend::RopeAngles): 0 divides the position by the timescale
// max_wavelength^(2i/D) (lerobot's apply_rope); 1 multiplies it by transformers' float32 inverse frequency
// 1 / base^(float(2i) / D); 2 the same inverse frequency rounded to bfloat16 (a model built in bfloat16).
TETHER_HD float rope_timescale(int64_t i, int64_t head_dim, float max_wavelength, int angles) {
  const float exponent = angles != 0 ? float(2 * i) / float(head_dim) : float(2.0 / double(head_dim)) * float(i);
  const float power = float(pow(double(max_wavelength), double(exponent)));
  if (angles == 0) return power;
  const float inverse = 1.0f / power;
  return angles == 2 ? bf16_bits_to_float(float_to_bf16_bits(inverse)) : inverse;
}

TETHER_HD float rope_angle(float position, float timescale, int angles) {
  return angles != 0 ? position * timescale : position / timescale;
}

// ---- attention: the online (streaming) softmax a flash-style kernel keeps per query row. Masked keys carry the
// lowest float as their score (not -inf), as the CPU backend's softmax does: once a real key is seen their weight is
// exactly zero, and a row with no real key at all averages every value uniformly, as the reference does.
struct OnlineSoftmax {
  float max;  // the largest score seen so far (-inf before the first)
  float sum;  // sum of exp(score - max) over the scores seen
};

TETHER_HD OnlineSoftmax online_softmax_start() { return {-bits_to_float(0x7f800000u), 0.0f}; }

TETHER_HD float masked_score(float dot, float scale, bool keep) {
  return keep ? dot * scale : -3.40282347e+38f;
}

// Folds a block's largest score in: returns the factor that rescales what was accumulated so far (sum and output).
TETHER_HD float online_softmax_rescale(OnlineSoftmax& s, float block_max) {
  const float new_max = block_max > s.max ? block_max : s.max;
  const float factor = s.max == new_max ? 1.0f : exp_f32(s.max - new_max);
  s.max = new_max;
  s.sum = s.sum * factor;
  return factor;
}

// One score's weight under the current maximum.
TETHER_HD float online_softmax_weight(const OnlineSoftmax& s, float score) { return exp_f32(score - s.max); }

// ---- the sampler's step

TETHER_HD float axpy(float x, float a, float v) { return x + a * v; }

// RTC guidance of one velocity element: the predicted clean sample x - t * v is pulled to the target.
TETHER_HD float rtc_guide(float x, float v, float target, float weight, float time, float guidance_weight) {
  const float x1 = x - time * v;
  const float err = (target - x1) * weight;
  return v - guidance_weight * err;
}

// Sinusoidal time embedding, element i of the sin half (i < half) and its cos partner: torch.linspace's fractions
// (the upper half counted back from the end), computed in double and rounded once.
TETHER_HD void time_embedding_pair(double time, int64_t i, int64_t half, double min_period, double max_period,
                                   float& sin_out, float& cos_out) {
  const double step = half > 1 ? 1.0 / double(half - 1) : 0.0;
  const double fraction = i < half / 2 ? double(i) * step : 1.0 - double(half - 1 - i) * step;
  const double period = min_period * pow(max_period / min_period, fraction);
  const double angle = (1.0 / period) * 2.0 * 3.14159265358979323846 * time;
  sin_out = float(sin(angle));
  cos_out = float(cos(angle));
}

}  // namespace tether::cuda_math
