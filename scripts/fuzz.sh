#!/usr/bin/env bash
# Builds the libFuzzer targets with clang and runs each for a bounded time (default 60 s each).
# Usage: scripts/fuzz.sh [seconds]
set -euo pipefail
cd "$(dirname "$0")/.."
seconds="${1:-60}"
command -v clang++ >/dev/null || { sudo=""; [ "$(id -u)" -ne 0 ] && sudo=sudo; $sudo apt-get install -y -qq clang; }
scripts/setup.sh release >/dev/null   # installs the library packages
[ -f build/fuzz/build.ninja ] || cmake --preset fuzz >/dev/null
cmake --build --preset fuzz
for target in build/fuzz/fuzz/fuzz_*; do
  [ -x "$target" ] || continue
  name=$(basename "$target")
  corpus="build/fuzz/corpus/$name"
  mkdir -p "$corpus"
  seeds=""
  case "$name" in
    *image*) seeds="tests/fixtures/vision" ;;
    *safetensors*) seeds="tests/fixtures/smolvla/cam1_stats" ;;
  esac
  echo "== $name ($seconds s)"
  "$target" -max_total_time="$seconds" -max_len=65536 "$corpus" $seeds 2>&1 | tail -n 2
done
