// GEMM through OpenBLAS's CBLAS (OpenMP build, so it shares the thread pool with the kernels).
// bench/GEMM.md records why OpenBLAS rather than oneDNN.
#include "backend/cpu/gemm.h"

#include <cblas.h>

#include <climits>
#include <cstring>
#include <string>

#include "core/error.h"

namespace tether::cpu {
namespace {

// Debian's OpenBLAS uses 32-bit BLAS integers; anything larger would silently wrap.
blasint to_blas_int(int64_t v, const char* what) {
  if (v < 0 || v > INT_MAX) {
    throw Error(ErrorCode::invalid_argument, std::string("gemm: ") + what + " = " + std::to_string(v) +
                                                 " is outside the BLAS integer range");
  }
  return static_cast<blasint>(v);
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
  to_blas_int(m, "m");
  to_blas_int(n, "n");
  to_blas_int(k, "k");
  if (m == 0 || n == 0) return;
  // Row-major: op(A) is m x k, stored as m rows of k (or, transposed, k rows of m).
  check_ld(lda, trans_a ? m : k, "lda");
  check_ld(ldb, trans_b ? k : n, "ldb");
  check_ld(ldc, n, "ldc");
  cblas_sgemm(CblasRowMajor, trans_a ? CblasTrans : CblasNoTrans, trans_b ? CblasTrans : CblasNoTrans,
              static_cast<blasint>(m), static_cast<blasint>(n), static_cast<blasint>(k), alpha, a,
              to_blas_int(lda, "lda"), b, to_blas_int(ldb, "ldb"), beta, c, to_blas_int(ldc, "ldc"));
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
  // Computed once: the core name is only known after OpenBLAS picked its kernels at load time.
  static const std::string name = [] {
    std::string config = openblas_get_config();
    std::string core = openblas_get_corename();
    return config + " (kernels: " + core + ", OpenMP)";
  }();
  return name.c_str();
}

int blas_threads() { return openblas_get_num_threads(); }

}  // namespace tether::cpu
