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

echo "tether (bf16): $iterations runs after $warmup warm-up..." >&2
build/release/tether bench "$checkpoint" "${image_args[@]}" --state="$state" --instruction "$instruction" \
  --noise "$work/noise.safetensors" --warmup "$warmup" --iterations "$iterations" --json --precision bf16 \
  --out "$work/tether_bf16.safetensors" > "$work/tether_bf16.json"

tools/oracle/run.sh - "$work" <<'PY'
import json, sys
from safetensors.torch import load_file
w = sys.argv[1]
ref = json.load(open(w + "/ref.json"))
a = load_file(w + "/ref.safetensors")["actions"]
r_ms = ref["median_ms"]
print(f"{'engine':<22}{'median ms':>12}{'speed-up':>10}{'peak RSS MB':>14}{'RSS ratio':>11}{'max |diff| vs lerobot':>24}")
print(f"{'lerobot (PyTorch fp32)':<22}{r_ms:>12.1f}{1.0:>9.2f}x{ref['peak_rss_mb']:>14.0f}{1.0:>11.2f}{'-':>24}")
for name, tag in (("tether fp32", "tether"), ("tether bf16", "tether_bf16")):
    t = json.load(open(f"{w}/{tag}.json"))
    b = load_file(f"{w}/{tag}.safetensors")["actions"]
    diff = (a.reshape(b.shape) - b).abs().max().item()
    t_ms = t["latency_ms"]["p50"]
    print(f"{name:<22}{t_ms:>12.1f}{r_ms / t_ms:>9.2f}x{t['peak_rss_mb']:>14.0f}{t['peak_rss_mb'] / ref['peak_rss_mb']:>11.2f}{diff:>24.3e}")
    print("    stages ms: " + "  ".join(f"{k} {v:.1f}" for k, v in t["stages_ms"].items()))
print(f"max |action| {a.abs().max().item():.3f} (robot units)")
PY
