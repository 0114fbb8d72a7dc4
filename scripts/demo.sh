#!/usr/bin/env bash
# Builds Tether (installing what is missing) and serves the bundled demo policy: starts `tether serve`, sends it
# one observation (the sample picture, a state, an instruction) over HTTP and prints the action chunk. From a
# terminal the server then keeps running on http://127.0.0.1:8000 until Ctrl-C; without one (or with --once) it
# shuts down cleanly after the request.
# The demo checkpoint has RANDOM weights: it shows the pipeline, not a trained behaviour.
set -euo pipefail
cd "$(dirname "$0")/.."
once=0
[ -t 0 ] || once=1
[ "${1:-}" = "--once" ] && once=1
port="${TETHER_DEMO_PORT:-8000}"
scripts/setup.sh release tether   # the binary alone: tests and benchmarks build with scripts/test.sh
build/release/tether serve models/demo/smolvla-demo --port "$port" > /tmp/tether-demo.$$ &
server=$!
trap 'kill -TERM $server 2>/dev/null || true; wait $server 2>/dev/null || true; rm -f /tmp/tether-demo.$$' EXIT
for _ in $(seq 100); do
  curl -sf "http://127.0.0.1:$port/health" >/dev/null && break
  kill -0 $server 2>/dev/null || { echo "demo: the server exited" >&2; exit 1; }
  sleep 0.1
done
echo "== POST /act (instruction 'pick up the red cube and put it in the blue bowl', models/demo/sample.png)"
printf '{"instruction": "pick up the red cube and put it in the blue bowl", "state": [0, 90, 90, 45, 0, 20], "seed": 7, "images": {"front": "%s"}}' \
  "$(base64 -w0 models/demo/sample.png)" |
  curl -sS "http://127.0.0.1:$port/act" -H 'Content-Type: application/json' --data-binary @- > /tmp/tether-demo-act.$$
python3 - /tmp/tether-demo-act.$$ <<'PY'
import json, sys
r = json.load(open(sys.argv[1]))
if "error" in r:
    sys.exit("demo: /act failed: " + json.dumps(r["error"]))
print("action chunk %d x %d (robot units), first 5 steps:" % (r["num_actions"], r["action_dim"]))
for row in r["actions"][:5]:
    print("  " + " ".join("%9.3f" % v for v in row))
print("latency ms: " + "  ".join("%s %.1f" % kv for kv in r["latency_ms"].items()))
print("inference_mode %s  model_hash %s...  request_id %s" % (json.dumps(r["inference_mode"]), r["model_hash"][:23], r["request_id"]))
PY
rm -f /tmp/tether-demo-act.$$
if [ "$once" = 1 ]; then
  exit 0
fi
echo "== serving the demo policy on http://127.0.0.1:$port (endpoints: /act /health /ready /live /config /metrics); Ctrl-C stops"
wait $server
