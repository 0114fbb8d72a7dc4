#!/usr/bin/env bash
# SmolVLA on CPU, Tether against upstream lerobot (PyTorch, fp32) in one run: same full-size checkpoint, same
# images, state, instruction and noise. Prints both latencies, their ratio, both peak RSS values and the max |diff|
# between the two action chunks.
# Usage: bench/smolvla_cpu.sh [--iterations N] [--warmup N] [--checkpoint DIR]
set -euo pipefail
cd "$(dirname "$0")/.."
iterations=5
warmup=1
ref_iterations=3
cache="${TETHER_CACHE:-$HOME/.cache/tether}"
checkpoint="$cache/checkpoints/smolvla-full-random"
while [ $# -gt 0 ]; do
  case "$1" in
    --iterations) iterations="$2"; shift 2 ;;
    --ref-iterations) ref_iterations="$2"; shift 2 ;;
    --warmup) warmup="$2"; shift 2 ;;
    --checkpoint) checkpoint="$2"; shift 2 ;;
    *) echo "unknown argument $1" >&2; exit 2 ;;
  esac
done

scripts/setup.sh release >/dev/null
tools/oracle/setup.sh >/dev/null
[ -f "$checkpoint/model.safetensors" ] || tools/oracle/run.sh smolvla_oracle.py full-size --out "$checkpoint"

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
image=models/demo/sample.png
state="0.1,-0.2,0.3,0.0,0.5,-0.4"
instruction="pick up the red cube and put it in the blue bowl"
cameras=$(python3 -c "import json,sys; c=json.load(open(sys.argv[1])); print(' '.join(k for k,v in c['input_features'].items() if v['type']=='VISUAL'))" "$checkpoint/config.json")
image_args=()
for cam in $cameras; do image_args+=(--image "$cam=$PWD/$image"); done

# One noise tensor for both engines.
tools/oracle/run.sh - "$checkpoint" "$work/noise.safetensors" <<'PY'
import json, sys, torch
from safetensors.torch import save_file
cfg = json.load(open(sys.argv[1] + "/config.json"))
g = torch.Generator().manual_seed(1234)
save_file({"noise": torch.randn((1, cfg["chunk_size"], cfg["max_action_dim"]), generator=g)}, sys.argv[2])
PY

echo "lerobot (PyTorch fp32, $(nproc) threads): $ref_iterations runs after $warmup warm-up..." >&2
tools/oracle/run.sh bench/lerobot_reference.py --checkpoint "$checkpoint" "${image_args[@]}" --state "$state" \
  --instruction "$instruction" --noise "$work/noise.safetensors" --warmup "$warmup" --iterations "$ref_iterations" \
  --out "$work/ref.safetensors" > "$work/ref.json"
echo "tether (fp32): $iterations runs after $warmup warm-up..." >&2
build/release/tether bench "$checkpoint" "${image_args[@]}" --state="$state" --instruction "$instruction" \
  --noise "$work/noise.safetensors" --warmup "$warmup" --iterations "$iterations" --json \
  --out "$work/tether.safetensors" > "$work/tether.json"

tools/oracle/run.sh - "$work" <<'PY'
import json, sys
from safetensors.torch import load_file
w = sys.argv[1]
ref, tet = json.load(open(w + "/ref.json")), json.load(open(w + "/tether.json"))
a, b = load_file(w + "/ref.safetensors")["actions"], load_file(w + "/tether.safetensors")["actions"]
diff = (a.reshape(b.shape) - b).abs().max().item()
r_ms, t_ms = ref["median_ms"], tet["latency_ms"]["p50"]
print(f"{'engine':<22}{'median ms':>12}{'peak RSS MB':>14}")
print(f"{'lerobot (PyTorch)':<22}{r_ms:>12.1f}{ref['peak_rss_mb']:>14.0f}")
print(f"{'tether fp32':<22}{t_ms:>12.1f}{tet['peak_rss_mb']:>14.0f}")
print(f"speed-up {r_ms / t_ms:.2f}x   RSS ratio {tet['peak_rss_mb'] / ref['peak_rss_mb']:.2f}   max |diff| {diff:.3e}")
print("tether stages ms: " + "  ".join(f"{k} {v:.1f}" for k, v in tet["stages_ms"].items()))
PY
