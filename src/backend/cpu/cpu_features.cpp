// CPU feature detection and the one ISA cap (TETHER_MAX_CPU_ISA) that lets a machine test every lower path.
#include "backend/cpu/cpu_features.h"

#include <oneapi/dnnl/dnnl.hpp>

#include <algorithm>
#include <cctype>
#include <cstdlib>

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
  // widening the weights to float32, and refuses bf16 below AVX-512.
  p.native_bf16 = p.effective >= CpuIsa::avx512_bf16 && p.native_bf16_onednn;
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

std::string cpu_paths_summary() {
  const CpuPaths& p = cpu_paths();
  std::string s = std::string(isa_name(p.effective)) + " (detected " + isa_name(p.detected);
  if (!p.cap.empty()) s += ", capped by TETHER_MAX_CPU_ISA=" + p.cap;
  return s + "; oneDNN " + p.onednn_isa + ")";
}

}  // namespace tether::cpu
