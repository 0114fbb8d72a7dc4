#!/usr/bin/env bash
# A VLA family on CPU, Tether against upstream lerobot (PyTorch, fp32) in one run: same full-size random-weight
# checkpoint, same images, state, instruction and noise. lerobot runs first and exits before Tether loads (a full-size
# pi0 needs ~14 GB in fp32 in either engine). Prints both latencies, their ratio, both peak RSS values and the
# max |diff| between the two action chunks, for Tether at fp32, bf16 and fp16 (which path each took is printed), and
# the fraction of the machine's measured fp32 GEMM peak.
# TETHER_MAX_CPU_ISA=AVX2 (with ONEDNN_MAX_CPU_ISA=AVX2) measures the AVX2 paths on any CPU.
# Usage: bench/vla_cpu.sh --family smolvla|pi0|pi05|gr00t_n17 [--iterations N] [--warmup N] [--ref-iterations N]
#        [--checkpoint DIR]    (bench/smolvla_cpu.sh, bench/pi0_cpu.sh, bench/pi05_cpu.sh and bench/gr00t_cpu.sh pass
#        the family)
set -euo pipefail
cd "$(dirname "$0")/.."
iterations=5
warmup=1
ref_iterations=3
cache="${TETHER_CACHE:-$HOME/.cache/tether}"
family=""
checkpoint=""
while [ $# -gt 0 ]; do
  case "$1" in
    --family) family="$2"; shift 2 ;;
    --iterations) iterations="$2"; shift 2 ;;
    --ref-iterations) ref_iterations="$2"; shift 2 ;;
    --warmup) warmup="$2"; shift 2 ;;
    --checkpoint) checkpoint="$2"; shift 2 ;;
    *) echo "unknown argument $1" >&2; exit 2 ;;
  esac
done

case "$family" in
  smolvla) generate=(smolvla_oracle.py full-size) ;;
  pi0|pi05)
    generate=(pi_oracle.py full-size --family "$family")
    # The PaliGemma tokenizer both engines load by its hub id: the oracle's stand-in, in its hub cache.
    export HF_HUB_CACHE="$PWD/tests/fixtures/paligemma_hub" ;;
  gr00t_n17)
    generate=(gr00t_oracle.py full-size)
    # Its Qwen3-VL backbone repository (the oracle's stand-in under the real id, real sizes), as a hub cache.
    export HF_HUB_CACHE="$cache/gr00t_hub" ;;
  *) echo "--family must be smolvla, pi0, pi05 or gr00t_n17" >&2; exit 2 ;;
esac
checkpoint="${checkpoint:-$cache/checkpoints/$family-full-random}"

scripts/setup.sh release >/dev/null
# Under the AVX2 cap the reference is capped too (PyTorch's CPU matmuls go through MKL and oneDNN), so both engines
# run what an AVX2-only CPU would; so is OpenBLAS, one of the candidates for the GEMM peak (it picks AVX-512 kernels on
# the CPUs it knows, which would put the AVX2 floor out of reach).
if [ "${TETHER_MAX_CPU_ISA:-}" != "" ] && [ "${TETHER_MAX_CPU_ISA^^}" = AVX2 ]; then
  export ONEDNN_MAX_CPU_ISA="${ONEDNN_MAX_CPU_ISA:-AVX2}" MKL_ENABLE_INSTRUCTIONS="${MKL_ENABLE_INSTRUCTIONS:-AVX2}" \
    OPENBLAS_CORETYPE="${OPENBLAS_CORETYPE:-Haswell}"
fi
tools/oracle/setup.sh >/dev/null
if [ "$family" = gr00t_n17 ] && [ ! -d "$HF_HUB_CACHE/models--nvidia--Cosmos-Reason2-2B" ]; then
  hub_tmp=$(mktemp -d)
  tools/oracle/run.sh gr00t_oracle.py hub --out "$hub_tmp" --full-out "$HF_HUB_CACHE"
  rm -rf "$hub_tmp"
fi
[ -f "$checkpoint/config.json" ] || tools/oracle/run.sh "${generate[@]}" --out "$checkpoint"

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
image=models/demo/sample.png
instruction="pick up the red cube and put it in the blue bowl"
# The cameras and a state of the checkpoint's width, in robot units near its statistics' centre: from the lerobot
# config's features, or (GR00T) from the processor config's only embodiment and its statistics.
read -r cameras_line state < <(python3 bench/checkpoint_inputs.py "$checkpoint")
cameras=${cameras_line//,/ }
image_args=()
for cam in $cameras; do image_args+=(--image "$cam=$PWD/$image"); done

# One noise tensor for both engines.
tools/oracle/run.sh - "$checkpoint" "$work/noise.safetensors" <<'PY'
import json, sys, torch
from safetensors.torch import save_file
cfg = json.load(open(sys.argv[1] + "/config.json"))
g = torch.Generator().manual_seed(1234)
rows = cfg["chunk_size"] if "chunk_size" in cfg else cfg["action_horizon"]  # GR00T samples its action horizon
save_file({"noise": torch.randn((1, rows, cfg["max_action_dim"]), generator=g)}, sys.argv[2])
PY

echo "$family: lerobot (PyTorch fp32, $(nproc) threads): $ref_iterations runs after $warmup warm-up..." >&2
tools/oracle/run.sh bench/lerobot_reference.py --checkpoint "$checkpoint" "${image_args[@]}" --state="$state" \
  --instruction "$instruction" --noise "$work/noise.safetensors" --warmup "$warmup" --iterations "$ref_iterations" \
  --out "$work/ref.safetensors" > "$work/ref.json"
# fp32, then both half-precision paths. bf16 runs natively where the CPU's bf16 dot product measures faster than its
# fp32 FMA (see `tether doctor`); elsewhere (or under TETHER_MAX_CPU_ISA=AVX2) it keeps bf16 weights widened to fp32
# in the kernel, as fp16 always does.
for precision in fp32 bf16 fp16; do
  echo "tether ($precision): $iterations runs after $warmup warm-up..." >&2
  build/release/tether bench "$checkpoint" "${image_args[@]}" --state="$state" --instruction "$instruction" \
    --noise "$work/noise.safetensors" --warmup "$warmup" --iterations "$iterations" --json --precision "$precision" \
    --out "$work/tether_$precision.safetensors" > "$work/tether_$precision.json"
done

# The machine's fp32 GEMM peak, measured now on the model's own GEMM shapes (best of OpenBLAS, oneDNN, panel).
echo "fp32 GEMM peak on this machine (bench/gemm_shapes)..." >&2
build/release/bench/gemm_shapes --model "$family" --threads "$(nproc)" --min-batch-ms 20 > "$work/gemm.txt"
peak=$(sed -n 's/^best measured fp32 GEMM rate: \([0-9.]*\) GFLOP.*/\1/p' "$work/gemm.txt")

tools/oracle/run.sh - "$work" "$peak" <<'PY'
import json, sys
from safetensors.torch import load_file
w, peak = sys.argv[1], float(sys.argv[2])
ref = json.load(open(w + "/ref.json"))
a = load_file(w + "/ref.safetensors")["actions"]
r_ms = ref["median_ms"]
fp32 = json.load(open(f"{w}/tether_fp32.json"))
gflop = fp32["gflop_per_chunk"]  # the same model: the same matrix-product work for either engine
def of_peak(ms):
    return gflop / (ms / 1e3) / peak
print(f"GEMM work per chunk {gflop:.1f} GFLOP; this machine's measured fp32 GEMM peak {peak:.1f} GFLOP/s "
      f"(floor {gflop / peak * 1e3:.0f} ms)")
print(f"{'engine':<22}{'median ms':>12}{'speed-up':>10}{'of GEMM peak':>14}{'peak RSS MB':>14}{'RSS ratio':>11}{'max |diff| vs lerobot':>24}")
print(f"{'lerobot (PyTorch fp32)':<22}{r_ms:>12.1f}{1.0:>9.2f}x{of_peak(r_ms):>14.2f}{ref['peak_rss_mb']:>14.0f}{1.0:>11.2f}{'-':>24}")
for precision in ("fp32", "bf16", "fp16"):
    t = json.load(open(f"{w}/tether_{precision}.json"))
    b = load_file(f"{w}/tether_{precision}.safetensors")["actions"]
    diff = (a.reshape(b.shape) - b).abs().max().item()
    t_ms = t["latency_ms"]["p50"]
    name = "tether " + t["inference_mode"].removeprefix("cpu-")
    print(f"{name:<22}{t_ms:>12.1f}{r_ms / t_ms:>9.2f}x{of_peak(t_ms):>14.2f}{t['peak_rss_mb']:>14.0f}{t['peak_rss_mb'] / ref['peak_rss_mb']:>11.2f}{diff:>24.3e}")
    print("    stages ms: " + "  ".join(f"{k} {v:.1f}" for k, v in t["stages_ms"].items()))
    print(f"    {t['compute']}; vs tether fp32: {t_ms / fp32['latency_ms']['p50']:.2f}x latency, "
          f"{t['peak_rss_mb'] / fp32['peak_rss_mb']:.2f}x peak RSS")
print("cpu: " + fp32["cpu_dispatch"])
print(f"max |action| {a.abs().max().item():.3f} (robot units)")
PY
