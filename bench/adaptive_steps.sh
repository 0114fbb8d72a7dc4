#!/usr/bin/env bash
# Adaptive denoise steps: for each threshold, `tether bench --adaptive-threshold` runs the same seeded observations
# with every step and adaptively, on the demo policy and on a full-size checkpoint (when present; --family picks which:
# smolvla by default, or gr00t_n17, whose 4 steps leave the check only steps 2 and 3). Prints one table.
# Usage: bench/adaptive_steps.sh [--thresholds "0.01 0.05 0.1 0.2"] [--iterations N] [--full-iterations N] [--demo-only]
#        [--family smolvla|gr00t_n17]
#        TETHER_BIN=path/to/tether uses that binary instead of building build/release.
set -euo pipefail
cd "$(dirname "$0")/.."
thresholds="0.01 0.05 0.1 0.2"
iterations=20
full_iterations=3
demo_only=0
cache="${TETHER_CACHE:-$HOME/.cache/tether}"
family=smolvla
while [ $# -gt 0 ]; do
  case "$1" in
    --thresholds) thresholds="$2"; shift 2 ;;
    --iterations) iterations="$2"; shift 2 ;;
    --full-iterations) full_iterations="$2"; shift 2 ;;
    --demo-only) demo_only=1; shift ;;
    --family) family="$2"; shift 2 ;;
    *) echo "unknown argument $1" >&2; exit 2 ;;
  esac
done
full="$cache/checkpoints/$family-full-random"
# GR00T N1.7's Qwen3-VL backbone files: the oracle's stand-in with the real sizes, as a hub cache (bench/gr00t_cpu.sh
# builds it with the checkpoint).
[ "$family" = gr00t_n17 ] && export HF_HUB_CACHE="$cache/gr00t_hub"
if [ -z "${TETHER_BIN:-}" ]; then
  scripts/setup.sh release >/dev/null
  TETHER_BIN=build/release/tether
fi

work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
image=models/demo/sample.png
instruction="pick up the red cube and put it in the blue bowl"

run_model() {  # name checkpoint iterations
  local name="$1" checkpoint="$2" iters="$3" args=()
  local cameras state
  read -r cameras state < <(python3 bench/checkpoint_inputs.py "$checkpoint")
  for cam in ${cameras//,/ }; do args+=(--image "$cam=$PWD/$image"); done
  for t in $thresholds; do
    echo "$name: threshold $t ($iters iterations)..." >&2
    "$TETHER_BIN" bench "$checkpoint" "${args[@]}" --state="$state" --instruction "$instruction" --seed 1 \
      --warmup 1 --iterations "$iters" --adaptive-threshold "$t" --json > "$work/$name-$t.json"
  done
}

run_model demo models/demo/smolvla-demo "$iterations"
if [ "$demo_only" = 1 ]; then
  :
elif [ -f "$full/config.json" ]; then
  run_model full-size "$full" "$full_iterations"
else
  echo "skipping the full-size checkpoint: $full not found (bench/${family%_n17}_cpu.sh makes it)" >&2
fi

python3 - "$work" <<'PY'
import glob, json, os, sys
rows = []
for path in glob.glob(os.path.join(sys.argv[1], "*.json")):
    name = os.path.basename(path).rsplit("-", 1)[0]
    r = json.load(open(path))
    a = r["adaptive"]
    rows.append((name != "demo", a["threshold"], name, r, a))
print("| model | threshold | steps used mean (min-max) of N | ms all steps | ms adaptive | denoise ms all -> adaptive | max \\|diff\\| (robot units) | max \\|action\\| |")
print("|---|---:|---:|---:|---:|---:|---:|---:|")
for _, t, name, r, a in sorted(rows, key=lambda x: (x[0], x[1])):
    s = a["steps_used"]
    print(f"| {name} | {t:g} | {s['mean']:.2f} ({s['min']:.0f}-{s['max']:.0f}) of {a['num_steps']} "
          f"| {a['latency_ms']['full']:.1f} | {a['latency_ms']['adaptive']:.1f} "
          f"| {a['denoise_ms']['full']:.1f} -> {a['denoise_ms']['adaptive']:.1f} "
          f"| {a['max_abs_diff']:.3g} | {a['max_abs_action']:.3g} |")
PY
