// Tether's own GEMM for y[M,N] = x[M,K] W[N,K]^T + b with the weights stored in float32, bfloat16 or float16 and
// widened to float32 inside the kernel: half-size weights on every CPU, whether or not it has bf16 instructions.
//
// Weights are packed once into panels of `panel_width` columns: panel p holds W[p*NR + j][k] at [k][j], zero-padded
// past N. Every output element is one fused multiply-add chain over k in index order, so a row's result does not
// depend on how many rows are computed with it (batch-invariant), on the thread count, or on the vector width:
// the AVX2, AVX-512 and portable kernels give bit-identical results. Internal to the CPU backend.
#pragma once

#include <cstdint>
#include <vector>

#include "backend/cpu/cpu_features.h"
#include "backend/cpu/huge_pages.h"

namespace tether::cpu::detail {

enum class PanelType { f32, bf16, f16 };

struct PanelGemmArgs {
  const float* x;  // [m, k], row stride lda
  int64_t m, k, lda;
  const void* panels;  // packed weights (elements of the panel type)
  int64_t n;           // real output columns
  const float* bias;   // [n padded to the panel width]
  float* y;            // [m, n], row stride ldy
  int64_t ldy;
  bool accumulate;     // y += x W^T + b instead of y = x W^T + b
};

using PanelGemmFn = void (*)(const PanelGemmArgs&);

struct PanelKernel {
  const char* name;  // "avx512", "avx2", "portable"
  int panel_width;   // NR
  PanelGemmFn f32, bf16, f16;
  PanelGemmFn get(PanelType t) const { return t == PanelType::bf16 ? bf16 : t == PanelType::f16 ? f16 : f32; }
};

// W [n, k] (row-major float32) in panels of `panel_width` columns, zero past n: float32 panels, or the bit patterns
// of bf16 / f16 (rounded to nearest even). bf16 rows are paired: the 32-bit word j of a panel row holds column j in
// its low half and column j + panel_width / 2 in its high half, so a kernel widens a whole row with a shift and a
// mask instead of two zero-extensions. The bias is zero-padded the same way (null: zeros).
PanelBuffer<float> pack_f32_panels(const float* w, int64_t n, int64_t k, int panel_width);
PanelBuffer<uint16_t> pack_half_panels(const float* w, int64_t n, int64_t k, int panel_width, PanelType type);
std::vector<float> pad_bias(const float* bias, int64_t n, int panel_width);

// C[m, n] = A[m, k] op(B) with the panel kernel's fixed-order chains, for operands that change every call (attention's
// scores and weighted sum): op(B)[q][j] = B[j * ldb + q] when trans_b (B holds n rows of k), else B[q * ldb + j].
// B is repacked into thread-local panels that grow once and are then reused, so steady-state calls allocate nothing.
// Zero terms anywhere in a chain leave it unchanged, which is what makes masked (padded) keys invisible.
// `bias` [n] (or null) is added last, as in the panel GEMM.
void gemm_fixed_order(int64_t m, int64_t n, int64_t k, const float* a, int64_t lda, const float* b, int64_t ldb,
                      bool trans_b, float* c, int64_t ldc, const float* bias = nullptr);

// gemm_fixed_order in two halves, for a B that several products share (attention's K and V, shared by every block
// of queries and every head of a group): pack it once, then multiply by the packed panels as often as needed. The
// results are bit-identical to gemm_fixed_order's. `panels` holds packed_b_floats(n, k) floats.
int64_t packed_b_floats(int64_t n, int64_t k);
void pack_b_panels(int64_t n, int64_t k, const float* b, int64_t ldb, bool trans_b, float* panels);
void gemm_packed_b(int64_t m, int64_t n, int64_t k, const float* a, int64_t lda, const float* panels, float* c,
                   int64_t ldc);

// The widest kernel the (capped) CPU runs.
const PanelKernel& panel_kernel();
// Every kernel this CPU can run, widest first (for tests that compare them).
std::vector<const PanelKernel*> panel_kernels();

// Kernel tables, one per translation unit (each compiled for its ISA); null where the ISA is not built.
const PanelKernel* panel_kernel_avx512();
const PanelKernel* panel_kernel_avx2();
const PanelKernel* panel_kernel_portable();

}  // namespace tether::cpu::detail
