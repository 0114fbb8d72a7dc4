#!/usr/bin/env bash
# Builds Tether (installing what is missing) and runs the default test suite: the C++ unit, parity and
# integration tests (CTest), then the Python client's unit tests and the real-HTTP integration tests of
# `tether serve` (pytest, in .venv). Under CI (CI=true) the build treats warnings as errors.
# The unit and parity labels then run a second time with every dispatch capped at AVX2 (Tether's own
# TETHER_MAX_CPU_ISA and oneDNN's ONEDNN_MAX_CPU_ISA), so the AVX2 path is checked whatever CPU this is, and,
# on a CPU with bf16 instructions that Tether measured too slow to use, with TETHER_BF16_GEMM=native, so the native
# bf16 path that such CPUs skip stays checked wherever it can run.
# Where nvcc is found the build includes the CUDA backend for every GPU target (cmake/cuda.cmake); its kernels'
# arithmetic is tested on the host here, and scripts/check_cuda_build.sh reads its machine code back.
# Slow suites (full-size benchmarks, fixture regeneration, sanitizers, fuzzing, the fresh-machine and arm64
# checks) have their own commands.
set -euo pipefail
cd "$(dirname "$0")/.."
preset=release
[ "${CI:-}" = "true" ] && preset=ci
scripts/setup.sh "$preset"
scripts/python_env.sh
ctest --preset "$preset" -j"$(nproc)" --label-exclude slow "$@"
# The CUDA backend's machine code: every target built, no spills, no local memory in the hot kernels, fp32 kernels
# free of tensor-core math (one line and a skip in a build without nvcc).
scripts/check_cuda_build.sh "$preset"
TETHER_BINARY="build/$preset/tether" .venv/bin/python -m pytest -q python/tests
if [ "$(uname -m)" = x86_64 ]; then
  echo "== unit and parity tests again, dispatch capped at AVX2 (TETHER_MAX_CPU_ISA=AVX2 ONEDNN_MAX_CPU_ISA=AVX2)"
  TETHER_MAX_CPU_ISA=AVX2 ONEDNN_MAX_CPU_ISA=AVX2 ctest --preset "$preset" -j"$(nproc)" -L 'unit|parity' \
    --label-exclude slow "$@"
  doctor=$(build/"$preset"/tether doctor 2>/dev/null || true)
  if grep -q "bf16 dot product .* bf16 weights widened" <<<"$doctor"; then
    echo "== unit and parity tests again, native bf16 forced (TETHER_BF16_GEMM=native)"
    TETHER_BF16_GEMM=native ctest --preset "$preset" -j"$(nproc)" -L 'unit|parity' --label-exclude slow "$@"
  fi
fi
