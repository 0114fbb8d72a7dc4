#!/usr/bin/env bash
# Starts `tether serve` on a free port, waits for /health, runs bench/serve_load against it, then SIGTERMs it.
# Usage: bench/serve_load.sh CHECKPOINT CLIENTS REQUESTS_PER_CLIENT [tether serve flags...]
#   e.g. bench/serve_load.sh models/demo/smolvla-demo 16,1,4,16 40 --max-batch 8
# BUILD selects the build directory (default build/release).
set -euo pipefail
cd "$(dirname "$0")/.."
build="${BUILD:-build/release}"
ckpt=$1 clients=$2 requests=$3
shift 3
out=$(mktemp) err=$(mktemp)
"$build/tether" serve "$ckpt" --port 0 "$@" >"$out" 2>"$err" &
pid=$!
trap 'kill -TERM $pid 2>/dev/null || true; wait $pid 2>/dev/null || true; rm -f "$out" "$err"' EXIT
for _ in $(seq 1 600); do grep -q listening "$out" && break; sleep 0.1; done
port=$(sed -E 's/.*:([0-9]+)$/\1/' "$out")
for _ in $(seq 1 1200); do curl -sf "localhost:$port/health" >/dev/null && break; sleep 0.5; done
"$build/bench/serve_load" --port "$port" --clients "$clients" --requests "$requests"
