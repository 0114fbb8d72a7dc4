// What this CPU can run, capped by TETHER_MAX_CPU_ISA, decided once per process: which vector width Tether's own
// kernels use and whether bf16 GEMMs run natively (oneDNN) or with weights widened to float32 in the kernel.
#pragma once

#include <string>

namespace tether::cpu {

// Ordered: each level includes the ones below it. `neon` is aarch64's baseline (every ARMv8-A core has it).
enum class CpuIsa { neon, avx2, avx512, avx512_bf16, amx };

struct CpuPaths {
  CpuIsa detected = CpuIsa::avx2;   // what the CPU reports
  CpuIsa effective = CpuIsa::avx2;  // detected, lowered by TETHER_MAX_CPU_ISA
  std::string cap;                  // the TETHER_MAX_CPU_ISA value as given ("" when unset)
  std::string onednn_isa;           // the ISA oneDNN's kernels dispatch to (after its own cap)
  bool native_bf16 = false;         // bf16 GEMMs run on the CPU's bf16 instructions (oneDNN)
  bool native_bf16_onednn = false;  // oneDNN itself offers bf16 matmul on this machine at its cap
  // fp32 linear layers on Tether's panel GEMM (batch-invariant, bit-identical on every CPU) rather than oneDNN's
  // (whose blocking, and so its last bits, change with the row count on some ISAs). TETHER_FP32_GEMM=onednn|panel.
  bool fp32_panel = true;
};

// Decided on first use: parses TETHER_MAX_CPU_ISA (AVX2, AVX512_CORE, AVX512_CORE_BF16, AVX512_CORE_AMX, ALL,
// case-insensitive; short forms avx512, avx512_bf16, amx), and, unless ONEDNN_MAX_CPU_ISA is set, caps oneDNN at
// the same level, so one variable moves every path. Reads TETHER_FP32_GEMM too. An unknown value of either throws
// tether::Error (invalid_argument).
const CpuPaths& cpu_paths();

const char* isa_name(CpuIsa isa);
// One line for doctor / bench: "avx512_bf16 (detected avx512_bf16; oneDNN avx512_core_bf16)".
std::string cpu_paths_summary();

}  // namespace tether::cpu
