#!/usr/bin/env bash
# Builds Tether (installing what is missing) and runs the default test suite: the C++ unit, parity and
# integration tests (CTest), then the Python client's unit tests and the real-HTTP integration tests of
# `tether serve` (pytest, in .venv). Under CI (CI=true) the build treats warnings as errors.
# Slow suites (full-size benchmarks, fixture regeneration, sanitizers, fuzzing) have their own commands.
set -euo pipefail
cd "$(dirname "$0")/.."
preset=release
[ "${CI:-}" = "true" ] && preset=ci
scripts/setup.sh "$preset"
scripts/python_env.sh
ctest --preset "$preset" -j"$(nproc)" --label-exclude slow "$@"
TETHER_BINARY="build/$preset/tether" .venv/bin/python -m pytest -q python/tests
