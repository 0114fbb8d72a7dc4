// Matrix multiplication on the CPU, delegated to a BLAS library (see bench/gemm_shapes for the choice).
// All matrices are row-major float32.
#pragma once

#include <cstdint>

namespace tether::cpu {

// C[M,N] = alpha * op(A) * op(B) + beta * C, op(X) = X or X^T; lda/ldb/ldc are row strides.
void gemm(bool trans_a, bool trans_b, int64_t m, int64_t n, int64_t k, float alpha, const float* a, int64_t lda,
          const float* b, int64_t ldb, float beta, float* c, int64_t ldc);

// The nn.Linear convention: y[M,N] = x[M,K] * W[N,K]^T + bias[N] (bias may be null).
// With accumulate=true the product is added to y (fuses a residual add: y += x W^T + bias).
void linear(const float* x, int64_t m, int64_t k, const float* weight, const float* bias, int64_t n, float* y,
            bool accumulate = false);

// Name of the BLAS library in use and its thread count, for `doctor` and benchmark reports.
const char* blas_name();
int blas_threads();

}  // namespace tether::cpu
