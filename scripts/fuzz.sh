#!/usr/bin/env bash
# Builds the libFuzzer targets with clang (the fuzz preset instruments all of src/: coverage, ASan, UBSan) and runs
# each for a bounded time, one after the other, on one core, from seeds in tests/fixtures and fuzz/seeds.
# Usage: scripts/fuzz.sh [seconds per target, default 60] [target ...]     e.g. scripts/fuzz.sh 600
# Prints per target the coverage edges reached and the findings: crash-, leak-, timeout- and oom- files in
# build/fuzz/findings/<target>/ (emptied at the start of each run). The edges are libFuzzer's `cov:` on the last line
# of a plain (non-fork) run over the corpus and seeds after the fuzzing: fork mode's own `cov:` counts differently
# and is not comparable between runs.
# Full logs: build/fuzz/logs/<target>.log. The corpus grown by earlier runs (build/fuzz/corpus/<target>/) is kept.
# Exit status 1 when any target has findings.
set -euo pipefail
cd "$(dirname "$0")/.."
seconds="${1:-60}"
shift || true
command -v clang++ >/dev/null || { sudo=""; [ "$(id -u)" -ne 0 ] && sudo=sudo; $sudo apt-get install -y -qq clang; }
# Configuring applies the preset's flags to an existing build directory too. It fails when a library package is
# missing: scripts/setup.sh installs them (and builds the release preset).
cmake --preset fuzz >/dev/null || { scripts/setup.sh release >/dev/null && cmake --preset fuzz >/dev/null; }

if [ $# -gt 0 ]; then
  targets=("$@")
else
  targets=()
  for src in fuzz/fuzz_*.cpp; do targets+=("$(basename "$src" .cpp)"); done
fi
cmake --build --preset fuzz --target "${targets[@]}"

# Seeds. libFuzzer reads at most -max_len bytes of each, so a large safetensors file still seeds its header. The
# large fixtures are packed in git (this preset builds no tests, which would expand them).
python3 scripts/fixture_packs.py unpack
seeds_for() {
  case "$1" in
    fuzz_safetensors_header)
      local dir=build/fuzz/seeds/$1
      rm -rf "$dir" && mkdir -p "$dir"
      find tests/fixtures -name '*.safetensors' -print0 |
        while IFS= read -r -d '' f; do cp "$f" "$dir/$(echo "$f" | tr / _)"; done
      echo "$dir" ;;
    fuzz_image_decode) echo "tests/fixtures/vision/images tests/fixtures/vision/bad" ;;
    fuzz_act_request) echo "fuzz/seeds/act_request" ;;
    fuzz_act_msgpack_request) echo "fuzz/seeds/act_msgpack_request" ;;
    fuzz_kserve_request) echo "fuzz/seeds/kserve_request" ;;
    fuzz_openpi_request) echo "fuzz/seeds/openpi_request" ;;
    fuzz_gr00t_request) echo "fuzz/seeds/gr00t_request" ;;
    fuzz_zmq_request) echo "fuzz/seeds/zmq_request" ;;
    fuzz_npy) echo "fuzz/seeds/npy" ;;
  esac
}

count() { find "$findings" -maxdepth 1 -name "$1-*" | wc -l; }
summary=()
found_any=0
for name in "${targets[@]}"; do
  bin="build/fuzz/fuzz/$name"
  corpus="build/fuzz/corpus/$name"
  findings="build/fuzz/findings/$name"
  log="build/fuzz/logs/$name.log"
  mkdir -p "$corpus" "$(dirname "$log")"
  rm -rf "$findings" && mkdir -p "$findings"
  dict=()
  [ -f "fuzz/dicts/$name.dict" ] && dict=(-dict="fuzz/dicts/$name.dict")
  # shellcheck disable=SC2046  # the seed list is space-separated directories
  seed_dirs=($(seeds_for "$name") "fuzz/regressions/$name")
  echo "== $name ($seconds s, log $log)"
  # Fork mode with one job: a crash, leak, timeout or OOM is saved and the run goes on for its full time.
  rc=0
  "$bin" -fork=1 -ignore_crashes=1 -ignore_timeouts=1 -ignore_ooms=1 \
    -max_total_time="$seconds" -max_len=65536 -rss_limit_mb=2048 -timeout=10 -print_funcs=0 \
    -artifact_prefix="$findings/" "${dict[@]}" "$corpus" "${seed_dirs[@]}" >"$log" 2>&1 || rc=$?
  # Coverage of what the run kept: every corpus input and seed executed once, without fork mode.
  "$bin" -runs=0 -rss_limit_mb=2048 -timeout=10 -print_funcs=0 "$corpus" "${seed_dirs[@]}" >"$log.cov" 2>&1 || true
  edges=$(grep -E 'cov: [0-9]+' "$log.cov" | tail -n 1 | sed -E 's/.*cov: ([0-9]+).*/\1/')
  crashes=$(count crash) leaks=$(count leak) timeouts=$(count timeout) ooms=$(count oom)
  total=$((crashes + leaks + timeouts + ooms))
  [ "$total" -gt 0 ] && found_any=1
  line="$name: ${edges:-?} edges, findings: $total (crash $crashes, leak $leaks, timeout $timeouts, oom $ooms)"
  [ "$rc" -ne 0 ] && [ "$total" -eq 0 ] && line="$line, libFuzzer exited with $rc (see the log)" && found_any=1
  echo "$line"
  find "$findings" -maxdepth 1 -type f | sort | head -n 10 | sed 's/^/  /'
  summary+=("$line")
done
echo "== summary"
printf '%s\n' "${summary[@]}"
exit "$found_any"
