// Branch-free float32 math written once for every backend: the CPU backend's vectorised kernels (libm calls are not
// vectorised without -ffast-math; the selects need -fno-trapping-math to be if-converted) and the CUDA kernels, whose
// activations then agree with the CPU's to the bit.
#pragma once

#include <cstdint>
#include <cstring>
#if __cplusplus >= 202002L
#include <bit>
#endif

#if defined(__CUDACC__)
#define TETHER_HD __host__ __device__ __forceinline__
#else
#define TETHER_HD inline
#endif

namespace tether::float_math {

TETHER_HD float bits_to_float(uint32_t bits) {
#if defined(__CUDA_ARCH__)
  return __uint_as_float(bits);
#elif __cplusplus >= 202002L
  return std::bit_cast<float>(bits);
#else
  float f;
  std::memcpy(&f, &bits, sizeof f);
  return f;
#endif
}

TETHER_HD uint32_t float_to_bits(float f) {
#if defined(__CUDA_ARCH__)
  return __float_as_uint(f);
#elif __cplusplus >= 202002L
  return std::bit_cast<uint32_t>(f);
#else
  uint32_t bits;
  std::memcpy(&bits, &f, sizeof bits);
  return bits;
#endif
}

// exp(x) to within about 2 ulp over the whole float range: Cody-Waite reduction by ln 2 and a degree-7
// polynomial (Cephes' expf coefficients). Returns 0 below ln(FLT_MIN) instead of a denormal and +inf
// above ln(FLT_MAX); both differ from the exact result by less than FLT_MIN or are exact.
TETHER_HD float exp_f32(float x) {
  const float kLo = -87.33654475f;   // ln(FLT_MIN): the smallest argument with a normal result
  const float kHi = 88.72283905f;    // ln(FLT_MAX)
  const float kLog2e = 1.44269504088896341f;
  const float kLn2Hi = 0.693359375f;  // few mantissa bits, so n * kLn2Hi is exact
  const float kLn2Lo = -2.12194440e-4f;
  float xc = x < kLo ? kLo : x;
  xc = xc > kHi ? kHi : xc;
  // Round to nearest by adding and removing 1.5 * 2^23 (valid for |v| < 2^22; needs no libm call).
  const float kRound = 12582912.0f;
  float n = (xc * kLog2e + kRound) - kRound;
  float r = xc - n * kLn2Hi;
  r = r - n * kLn2Lo;
  float p = 1.9875691500e-4f;
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  p = p * (r * r) + r + 1.0f;
  // 2^n for n up to 128: split off one factor of 2 so the exponent field never reaches the inf code.
  int32_t ni = static_cast<int32_t>(n);
  int32_t n1 = ni > 127 ? 127 : ni;
  float two_n1 = bits_to_float(uint32_t(n1 + 127) << 23);
  float extra = ni > 127 ? 2.0f : 1.0f;
  float result = p * two_n1 * extra;
  result = x < kLo ? 0.0f : result;
  result = x > kHi ? bits_to_float(0x7f800000u) : result;
  return x != x ? x : result;  // NaN in, NaN out
}

// tanh(x) to within about 2 ulp: an odd polynomial below |x| = 0.625 (Cephes' tanhf coefficients),
// 1 - 2 / (exp(2|x|) + 1) above, both evaluated and one selected so the loop stays branch-free.
TETHER_HD float tanh_f32(float x) {
  const float ax = x < 0.0f ? -x : x;
  const float z = x * x;
  float p = -5.70498872745e-3f;
  p = p * z + 2.06390887954e-2f;
  p = p * z - 5.37397155531e-2f;
  p = p * z + 1.33314422036e-1f;
  p = p * z - 3.33332819422e-1f;
  const float small = p * z * x + x;
  const float big_abs = 1.0f - 2.0f / (exp_f32(2.0f * ax) + 1.0f);
  const float big = x < 0.0f ? -big_abs : big_abs;
  return ax < 0.625f ? small : big;
}

}  // namespace tether::float_math
