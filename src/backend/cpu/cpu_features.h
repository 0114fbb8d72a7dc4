// What this CPU can run, capped by TETHER_MAX_CPU_ISA, decided once per process: which vector width Tether's own
// kernels use and whether bf16 GEMMs run natively (oneDNN) or with weights widened to float32 in the kernel.
// Having bf16 instructions is not enough for native: they must also be faster than fp32 here, which is measured.
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
  // Flop rate of the CPU's bf16 dot product (VDPBF16PS) over its fp32 FMA, measured once when the (capped) CPU has
  // AVX512-BF16 without AMX; 0 when not measured. Native bf16 needs at least kMinNativeBf16Speed.
  double bf16_dot_speed = 0;
  std::string bf16_gemm;  // the TETHER_BF16_GEMM value as given ("" when unset): native or widened, not measured
  // fp32 linear layers on Tether's panel GEMM (batch-invariant, bit-identical on every CPU) rather than oneDNN's
  // (whose blocking, and so its last bits, change with the row count on some ISAs). TETHER_FP32_GEMM=onednn|panel.
  bool fp32_panel = true;
};

// Native bf16 must do at least this many times fp32's flops per second in the dot product itself: below it, the
// conversion of every input to bf16 eats the gain, and widening bf16 weights in the fp32 kernel is as fast and exact
// in its products. An Emerald Rapids VM without AMX measured 0.50 (VDPBF16PS issues at a quarter of the FMA rate
// there); on Zen 5, oneDNN's bf16 GEMM ran at twice its f32 rate (bench/GEMM.md), so its ratio should be near 2.
constexpr double kMinNativeBf16Speed = 1.3;

// Decided on first use: parses TETHER_MAX_CPU_ISA (AVX2, AVX512_CORE, AVX512_CORE_BF16, AVX512_CORE_AMX, ALL,
// case-insensitive; short forms avx512, avx512_bf16, amx), and, unless ONEDNN_MAX_CPU_ISA is set, caps oneDNN at
// the same level, so one variable moves every path. Reads TETHER_FP32_GEMM (panel, onednn) and TETHER_BF16_GEMM
// (native, widened: skips the measurement) too. An unknown value of any throws tether::Error (invalid_argument), and
// so does TETHER_BF16_GEMM=native where the capped CPU or oneDNN has no bf16 instructions.
const CpuPaths& cpu_paths();

// Why bf16 GEMMs widen the weights instead of running natively, for messages: "this CPU has no bf16 instructions",
// "this CPU's bf16 dot product measured 0.50x the fp32 FMA's flop rate, ...", ...; "" when they run natively.
std::string bf16_widened_reason();

const char* isa_name(CpuIsa isa);
// One line for doctor / bench: "avx512_bf16 (detected avx512_bf16; oneDNN avx512_core_bf16)".
std::string cpu_paths_summary();

}  // namespace tether::cpu
