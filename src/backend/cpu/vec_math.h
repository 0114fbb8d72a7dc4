// Branch-free float32 math that the compiler can vectorise (libm calls are not vectorised without
// -ffast-math; the selects need -fno-trapping-math to be if-converted). Internal to the CPU backend.
#pragma once

#include <bit>
#include <cstdint>

namespace tether::cpu::detail {

// exp(x) to within about 2 ulp over the whole float range: Cody-Waite reduction by ln 2 and a degree-7
// polynomial (Cephes' expf coefficients). Returns 0 below ln(FLT_MIN) instead of a denormal and +inf
// above ln(FLT_MAX); both differ from the exact result by less than FLT_MIN or are exact.
inline float exp_f32(float x) {
  constexpr float kLo = -87.33654475f;   // ln(FLT_MIN): the smallest argument with a normal result
  constexpr float kHi = 88.72283905f;    // ln(FLT_MAX)
  constexpr float kLog2e = 1.44269504088896341f;
  constexpr float kLn2Hi = 0.693359375f;  // few mantissa bits, so n * kLn2Hi is exact
  constexpr float kLn2Lo = -2.12194440e-4f;
  float xc = x < kLo ? kLo : x;
  xc = xc > kHi ? kHi : xc;
  // Round to nearest by adding and removing 1.5 * 2^23 (valid for |v| < 2^22; needs no libm call).
  constexpr float kRound = 12582912.0f;
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
  float two_n1 = std::bit_cast<float>(static_cast<int32_t>((n1 + 127) << 23));
  float extra = ni > 127 ? 2.0f : 1.0f;
  float result = p * two_n1 * extra;
  result = x < kLo ? 0.0f : result;
  result = x > kHi ? __builtin_inff() : result;
  return x != x ? x : result;  // NaN in, NaN out
}

// tanh(x) to within about 2 ulp: an odd polynomial below |x| = 0.625 (Cephes' tanhf coefficients),
// 1 - 2 / (exp(2|x|) + 1) above, both evaluated and one selected so the loop stays branch-free.
inline float tanh_f32(float x) {
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

}  // namespace tether::cpu::detail
