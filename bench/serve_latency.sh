#!/usr/bin/env bash
# Single-client latency of `tether serve`: continuous batching (--batch-timeout-ms 0, the default) against a 5 ms
# gathering window, both measured in the same run through bench/serve_load.sh (one keep-alive client, sequential
# POST /act). Prints each mode's p50 and p99 and the ratio window / continuous.
# Usage: bench/serve_latency.sh [CHECKPOINT] [REQUESTS]   (defaults: models/demo/smolvla-demo, 200)
set -euo pipefail
cd "$(dirname "$0")/.."
ckpt="${1:-models/demo/smolvla-demo}" requests="${2:-200}"
# The last table row for 1 client (the first is a warm-up pass): | clients | requests | req/s | p50 | p95 | p99 | mean batch | errors |
row() { bench/serve_load.sh "$ckpt" 1,1 "$requests" --batch-timeout-ms "$1" | grep -E '^\| 1 \|' | tail -1; }
window=$(row 5)
continuous=$(row 0)
field() { echo "$1" | awk -F'|' -v c="$2" '{gsub(/ /, "", $c); print $c}'; }
printf '%-22s %10s %10s %8s\n' mode "p50 (ms)" "p99 (ms)" errors
printf '%-22s %10s %10s %8s\n' "window 5 ms" "$(field "$window" 5)" "$(field "$window" 7)" "$(field "$window" 9)"
printf '%-22s %10s %10s %8s\n' "continuous" "$(field "$continuous" 5)" "$(field "$continuous" 7)" "$(field "$continuous" 9)"
awk -v a="$(field "$window" 5)" -v b="$(field "$continuous" 5)" -v c="$(field "$window" 7)" -v d="$(field "$continuous" 7)" \
  'BEGIN { printf "ratio window/continuous: p50 %.2fx, p99 %.2fx\n", a / b, c / d }'
