#!/usr/bin/env bash
# Builds Tether (installing what is missing) and runs the default test suite: unit, parity and integration
# tests. Under CI (CI=true) the build treats warnings as errors. Slow suites have their own commands.
set -euo pipefail
cd "$(dirname "$0")/.."
preset=release
[ "${CI:-}" = "true" ] && preset=ci
scripts/setup.sh "$preset"
ctest --preset "$preset" -j"$(nproc)" --label-exclude slow "$@"
