#!/usr/bin/env bash
# Peak RSS of `tether serve` on the full-size random GR00T N1.7 checkpoint with one embodiment and with two served from
# one process (--embodiment-tag a,b): the second embodiment should cost its category rows only. The two-embodiment
# checkpoint is the full-size one (bench/gr00t_cpu.sh writes it) with its sidecars copied for a second tag on another
# weights row, the weights linked, in a scratch directory. Each server answers one /act per embodiment before its
# VmHWM is read.
# Usage: bench/gr00t_embodiments_rss.sh      TETHER_BIN=path/to/tether uses that binary instead of build/release.
set -euo pipefail
cd "$(dirname "$0")/.."
cache="${TETHER_CACHE:-$HOME/.cache/tether}"
src="$cache/checkpoints/gr00t_n17-full-random"
[ -f "$src/config.json" ] || { echo "no $src: run bench/gr00t_cpu.sh first (it writes the checkpoint)" >&2; exit 2; }
export HF_HUB_CACHE="$cache/gr00t_hub"
if [ -z "${TETHER_BIN:-}" ]; then
  ./scripts/setup.sh release >/dev/null
  TETHER_BIN=build/release/tether
fi
dir="$(mktemp -d)"
trap 'rm -rf "$dir"' EXIT
for f in "$src"/model* "$src"/config.json; do ln -s "$f" "$dir/"; done
python3 - "$src" "$dir" <<'PY'
import json, sys
src, dst = sys.argv[1], sys.argv[2]
pc = json.load(open(f"{src}/processor_config.json"))
tags = pc["processor_kwargs"]["modality_configs"]
first = next(iter(tags))
tags["second_robot"] = tags[first]
json.dump(pc, open(f"{dst}/processor_config.json", "w"), indent=1)
stats = json.load(open(f"{src}/statistics.json"))
stats["second_robot"] = stats[first]
json.dump(stats, open(f"{dst}/statistics.json", "w"))
ids = json.load(open(f"{src}/embodiment_id.json"))
ids["second_robot"] = (ids[first] + 1) % 32
json.dump(ids, open(f"{dst}/embodiment_id.json", "w"))
PY
first="$(python3 -c "import json; print(next(iter(json.load(open('$src/embodiment_id.json')))))")"
state="$(python3 -c "
import json; s = json.load(open('$src/statistics.json'))['$first']['state']; print(sum(len(v['min']) for v in s.values()))")"
camera="$(python3 -c "
import json; print(json.load(open('$src/processor_config.json'))['processor_kwargs']['modality_configs']['$first']['video']['modality_keys'][0])")"
image="$(base64 -w0 models/demo/sample.png)"
zeros="$(python3 -c "print(','.join(['0'] * $state))")"
port=18765
measure() {  # tags
  "$TETHER_BIN" serve "$dir" --port "$port" --embodiment-tag "$1" >/dev/null 2>"$dir/serve.err" &
  local pid=$!
  for _ in $(seq 900); do curl -sf "localhost:$port/ready" >/dev/null && break; sleep 1; done
  for tag in ${1//,/ }; do
    curl -sf -o /dev/null -H 'Content-Type: application/json' "localhost:$port/act" \
      -d "{\"instruction\":\"pick\",\"state\":[$zeros],\"images\":{\"$camera\":\"$image\"},\"seed\":1,\"embodiment_tag\":\"$tag\"}"
  done
  local hwm
  hwm="$(awk '/VmHWM/ {print int($2 / 1024)}' "/proc/$pid/status")"
  kill "$pid"
  wait "$pid" || true
  printf '%-40s peak RSS %6d MB\n' "$1" "$hwm"
}
echo "binary: $TETHER_BIN; checkpoint: $src (fp32 compute, bf16 weights)"
measure "$first"
measure "$first,second_robot"
