// GEMM through oneDNN's sgemm (its OpenMP build, so it shares the thread pool with the kernels).
// bench/GEMM.md records why oneDNN: about 2x OpenBLAS on SmolVLA's shapes on this machine class, because
// Debian's OpenBLAS 0.3.21 does not recognise newer AVX-512 CPUs and falls back to AVX2 kernels.
#include "backend/cpu/gemm.h"

#include <dnnl.h>
#include <omp.h>

#include <climits>
#include <cstring>
#include <string>

#include "core/error.h"

namespace tether::cpu {
namespace {

void check_dim(int64_t v, const char* what) {
  if (v < 0 || v > INT_MAX) {
    throw Error(ErrorCode::invalid_argument, std::string("gemm: ") + what + " = " + std::to_string(v) +
                                                 " is outside the supported range");
  }
}

void check_ld(int64_t ld, int64_t cols, const char* what) {
  if (ld < (cols > 1 ? cols : 1)) {
    throw Error(ErrorCode::invalid_argument, std::string("gemm: ") + what + " = " + std::to_string(ld) +
                                                 " is smaller than the row length " + std::to_string(cols));
  }
}

}  // namespace

void gemm(bool trans_a, bool trans_b, int64_t m, int64_t n, int64_t k, float alpha, const float* a, int64_t lda,
          const float* b, int64_t ldb, float beta, float* c, int64_t ldc) {
  check_dim(m, "m");
  check_dim(n, "n");
  check_dim(k, "k");
  if (m == 0 || n == 0) return;
  // Row-major: op(A) is m x k, stored as m rows of k (or, transposed, k rows of m).
  check_ld(lda, trans_a ? m : k, "lda");
  check_ld(ldb, trans_b ? k : n, "ldb");
  check_ld(ldc, n, "ldc");
  const dnnl_status_t st =
      dnnl_sgemm(trans_a ? 'T' : 'N', trans_b ? 'T' : 'N', m, n, k, alpha, a, lda, b, ldb, beta, c, ldc);
  if (st != dnnl_success)
    throw Error(ErrorCode::internal, "gemm: oneDNN sgemm failed with status " + std::to_string(int(st)));
}

void linear(const float* x, int64_t m, int64_t k, const float* weight, const float* bias, int64_t n, float* y,
            bool accumulate) {
  if (m <= 0 || n <= 0) return;
  float beta = accumulate ? 1.0f : 0.0f;
  if (bias != nullptr) {
    // PyTorch's addmm seeds the output with the bias and lets the GEMM add the product to it (beta = 1);
    // doing the same keeps the rounding of (x W^T) + b identical in the non-accumulating case.
    if (accumulate) {
      for (int64_t i = 0; i < m; ++i) {
        float* row = y + i * n;
#pragma omp simd
        for (int64_t j = 0; j < n; ++j) row[j] += bias[j];
      }
    } else {
      for (int64_t i = 0; i < m; ++i) std::memcpy(y + i * n, bias, sizeof(float) * std::size_t(n));
    }
    beta = 1.0f;
  }
  gemm(false, true, m, n, k, 1.0f, x, k, weight, k, beta, y, n);
}

const char* blas_name() {
  static const std::string name = [] {
    const dnnl_version_t* v = dnnl_version();
    return "oneDNN " + std::to_string(v->major) + "." + std::to_string(v->minor) + "." + std::to_string(v->patch) +
           " (OpenMP)";
  }();
  return name.c_str();
}

int blas_threads() { return omp_get_max_threads(); }

}  // namespace tether::cpu
