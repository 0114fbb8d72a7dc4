// CPU feature detection and the one ISA cap (TETHER_MAX_CPU_ISA) that lets a machine test every lower path.
#include "backend/cpu/cpu_features.h"

#include <oneapi/dnnl/dnnl.hpp>

#include <algorithm>
#include <cctype>
#include <chrono>
#include <cstdio>
#include <cstdlib>

#if defined(__x86_64__)
#include <immintrin.h>
#endif

#include "core/error.h"

namespace tether::cpu {

namespace {

CpuIsa detect() {
#if defined(__x86_64__)
  __builtin_cpu_init();
  if (!__builtin_cpu_supports("avx512f") || !__builtin_cpu_supports("avx512bw") ||
      !__builtin_cpu_supports("avx512vl") || !__builtin_cpu_supports("avx512dq"))
    return CpuIsa::avx2;
  if (!__builtin_cpu_supports("avx512bf16")) return CpuIsa::avx512;
  // GCC 12's __builtin_cpu_supports has no AMX names: CPUID leaf 7 EDX bits 22 (AMX-BF16) and 24 (AMX-TILE).
  unsigned a = 7, b = 0, c = 0, d = 0;
  __asm__("cpuid" : "+a"(a), "=b"(b), "+c"(c), "=d"(d));
  const bool amx = (d >> 22 & 1) && (d >> 24 & 1);
  return amx ? CpuIsa::amx : CpuIsa::avx512_bf16;
#else
  return CpuIsa::neon;
#endif
}

std::string lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(), [](unsigned char ch) { return char(std::tolower(ch)); });
  return s;
}

CpuIsa parse_cap(const std::string& value, CpuIsa detected) {
  const std::string v = lower(value);
  if (v == "all") return detected;
#if defined(__x86_64__)
  if (v == "avx2") return CpuIsa::avx2;
  if (v == "avx512" || v == "avx512_core") return CpuIsa::avx512;
  if (v == "avx512_bf16" || v == "avx512_core_bf16") return CpuIsa::avx512_bf16;
  if (v == "amx" || v == "avx512_core_amx") return CpuIsa::amx;
  throw Error(ErrorCode::invalid_argument, "TETHER_MAX_CPU_ISA='" + value +
                                               "' is not one of AVX2, AVX512_CORE, AVX512_CORE_BF16, AVX512_CORE_AMX, ALL");
#else
  if (v == "neon" || v == "asimd") return CpuIsa::neon;
  throw Error(ErrorCode::invalid_argument, "TETHER_MAX_CPU_ISA='" + value + "' is not one of NEON, ALL on aarch64");
#endif
}

#if defined(__x86_64__)
// The two instructions the probe races, one step of one accumulator chain each.
struct Fp32Fma {
  __attribute__((target("avx512f"))) static __m512 step(__m512 acc) {
    return _mm512_fmadd_ps(acc, _mm512_set1_ps(0.25f), _mm512_set1_ps(0.5f));
  }
};
struct Bf16Dot {
  __attribute__((target("avx512f,avx512bf16"))) static __m512 step(__m512 acc) {
    const __m512bh a = _mm512_cvtne2ps_pbh(_mm512_set1_ps(0.25f), _mm512_set1_ps(0.25f));
    return _mm512_dpbf16_ps(acc, a, a);
  }
};

// Seconds for 8192 rounds of 16 independent chains of `Op` (enough chains to cover either instruction's latency), on
// registers, so only the issue rate counts. The empty asm keeps the chains from being folded or hoisted.
template <class Op>
__attribute__((target("avx512f,avx512bf16"))) double time_chains() {
  __m512 acc[16];
#pragma GCC unroll 16
  for (int i = 0; i < 16; ++i) acc[i] = _mm512_set1_ps(float(i));
  const auto t0 = std::chrono::steady_clock::now();
  for (int s = 0; s < 8192; ++s) {
#pragma GCC unroll 16
    for (int i = 0; i < 16; ++i) {
      acc[i] = Op::step(acc[i]);
      __asm__ volatile("" : "+v"(acc[i]));
    }
  }
  const double t = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  __m512 sum = acc[0];
#pragma GCC unroll 16
  for (int i = 1; i < 16; ++i) sum = _mm512_add_ps(sum, acc[i]);
  alignas(64) float lanes[16];
  _mm512_store_ps(lanes, sum);
  volatile float sink = lanes[0];
  (void)sink;
  return t;
}

// The bf16 dot product's flop rate over fp32 FMA's: VDPBF16PS does 32 multiply-adds per instruction, FMA 16. Whether
// a CPU issues VDPBF16PS as fast as FMA is a property of its microarchitecture that no feature flag reports, so it is
// measured (about 3 ms, once per process); the best of nine interleaved rounds of each, after a warm-up, keeps a busy
// machine's hiccups out.
double measure_bf16_dot_speed() {
  time_chains<Fp32Fma>(), time_chains<Bf16Dot>();
  double fma = 1e30, dot = 1e30;
  for (int round = 0; round < 9; ++round) {
    fma = std::min(fma, time_chains<Fp32Fma>());
    dot = std::min(dot, time_chains<Bf16Dot>());
  }
  return 2.0 * fma / dot;
}

const char* onednn_isa_name(dnnl::cpu_isa isa) {
  switch (isa) {
    case dnnl::cpu_isa::sse41: return "sse41";
    case dnnl::cpu_isa::avx: return "avx";
    case dnnl::cpu_isa::avx2: return "avx2";
    case dnnl::cpu_isa::avx2_vnni: return "avx2_vnni";
    case dnnl::cpu_isa::avx512_core: return "avx512_core";
    case dnnl::cpu_isa::avx512_core_vnni: return "avx512_core_vnni";
    case dnnl::cpu_isa::avx512_core_bf16: return "avx512_core_bf16";
    case dnnl::cpu_isa::avx512_core_amx: return "avx512_core_amx";
    default: return "other";
  }
}
#endif

CpuPaths decide() {
  CpuPaths p;
  p.detected = detect();
  p.effective = p.detected;
  if (const char* cap = std::getenv("TETHER_MAX_CPU_ISA"); cap && *cap) {
    p.cap = cap;
    p.effective = std::min(p.detected, parse_cap(p.cap, p.detected));
  }
#if defined(__x86_64__)
  // One cap for both: oneDNN follows Tether's unless its own variable says otherwise. It must be set before
  // oneDNN creates its first primitive, which is why every oneDNN user in the backend asks cpu_paths() first.
  const char* onednn_cap = std::getenv("ONEDNN_MAX_CPU_ISA");
  if (!p.cap.empty() && !(onednn_cap && *onednn_cap)) {
    const dnnl::cpu_isa to = p.effective == CpuIsa::amx           ? dnnl::cpu_isa::avx512_core_amx
                             : p.effective == CpuIsa::avx512_bf16 ? dnnl::cpu_isa::avx512_core_bf16
                             : p.effective == CpuIsa::avx512      ? dnnl::cpu_isa::avx512_core
                                                                  : dnnl::cpu_isa::avx2;
    dnnl::set_max_cpu_isa(to);
  }
  const dnnl::cpu_isa onednn = dnnl::get_effective_cpu_isa();
  p.onednn_isa = onednn_isa_name(onednn);
  p.native_bf16_onednn = onednn == dnnl::cpu_isa::avx512_core_bf16 || onednn == dnnl::cpu_isa::avx512_core_amx;
#else
  p.onednn_isa = "aarch64";
#endif
  // Native only where the CPU has bf16 instructions: oneDNN 2.6 also emulates bf16 on plain AVX-512, slower than
  // widening the weights to float32, and refuses bf16 below AVX-512. And only where they are faster than fp32: AMX
  // tiles are; VDPBF16PS alone is measured.
  const bool has_bf16 = p.effective >= CpuIsa::avx512_bf16 && p.native_bf16_onednn;
  if (const char* bf16 = std::getenv("TETHER_BF16_GEMM"); bf16 && *bf16) {
    p.bf16_gemm = lower(bf16);
    if (p.bf16_gemm != "native" && p.bf16_gemm != "widened")
      throw Error(ErrorCode::invalid_argument, "TETHER_BF16_GEMM='" + std::string(bf16) + "' is not one of native, widened");
    if (p.bf16_gemm == "native" && !has_bf16)
      throw Error(ErrorCode::invalid_argument, "TETHER_BF16_GEMM=native, but this CPU runs oneDNN at " + p.onednn_isa +
                                                   " (" + isa_name(p.effective) + "), without bf16 instructions");
    p.native_bf16 = p.bf16_gemm == "native";
  } else if (has_bf16 && p.effective == CpuIsa::amx) {
    p.native_bf16 = true;
  } else if (has_bf16) {
#if defined(__x86_64__)
    p.bf16_dot_speed = measure_bf16_dot_speed();
#endif
    p.native_bf16 = p.bf16_dot_speed >= kMinNativeBf16Speed;
  }
  if (const char* gemm = std::getenv("TETHER_FP32_GEMM"); gemm && *gemm) {
    const std::string g = lower(gemm);
    if (g != "panel" && g != "onednn")
      throw Error(ErrorCode::invalid_argument, "TETHER_FP32_GEMM='" + std::string(gemm) + "' is not one of panel, onednn");
    p.fp32_panel = g == "panel";
  }
  return p;
}

}  // namespace

const CpuPaths& cpu_paths() {
  static const CpuPaths paths = decide();
  return paths;
}

const char* isa_name(CpuIsa isa) {
  switch (isa) {
    case CpuIsa::neon: return "neon";
    case CpuIsa::avx2: return "avx2";
    case CpuIsa::avx512: return "avx512";
    case CpuIsa::avx512_bf16: return "avx512_bf16";
    case CpuIsa::amx: return "amx";
  }
  return "?";
}

std::string bf16_widened_reason() {
  const CpuPaths& p = cpu_paths();
  if (p.native_bf16) return "";
  if (p.effective < CpuIsa::avx512_bf16)
    return p.detected >= CpuIsa::avx512_bf16 ? "this CPU's bf16 instructions are capped by TETHER_MAX_CPU_ISA=" + p.cap
                                             : "this CPU has no bf16 instructions";
  if (!p.native_bf16_onednn) return "this CPU has bf16 instructions, but oneDNN runs at " + p.onednn_isa;
  if (p.bf16_gemm == "widened") return "TETHER_BF16_GEMM=widened";
  char speed[160];
  std::snprintf(speed, sizeof speed,
                "this CPU's bf16 dot product measured %.2fx the fp32 FMA's flop rate, below the %.1fx native bf16 needs",
                p.bf16_dot_speed, kMinNativeBf16Speed);
  return speed;
}

std::string cpu_paths_summary() {
  const CpuPaths& p = cpu_paths();
  std::string s = std::string(isa_name(p.effective)) + " (detected " + isa_name(p.detected);
  if (!p.cap.empty()) s += ", capped by TETHER_MAX_CPU_ISA=" + p.cap;
  s += "; oneDNN " + p.onednn_isa;
  if (p.bf16_dot_speed > 0) {
    char speed[96];
    std::snprintf(speed, sizeof speed, "; bf16 dot product %.2fx fp32 FMA: bf16 %s", p.bf16_dot_speed,
                  p.native_bf16 ? "native" : "weights widened");
    s += speed;
  } else if (!p.bf16_gemm.empty()) {
    s += "; TETHER_BF16_GEMM=" + p.bf16_gemm;
  }
  return s + ")";
}

}  // namespace tether::cpu
