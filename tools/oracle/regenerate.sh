#!/usr/bin/env bash
# Regenerates every committed oracle fixture and the demo policy (outside the default test run).
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
root="$(cd "$here/../.." && pwd)"
"$here/setup.sh"
# optional generators owned by the text and vision layers; run whichever exist
for gen in tokenizer_fixtures.py paligemma_tokenizer_fixtures.py vision_fixtures.py; do
  if [[ -f "$here/$gen" ]]; then
    echo "== $gen"
    "$here/run.sh" "$here/$gen"
  fi
done
echo "== GR00T N1.7 camera-frame fixtures (cv2 INTER_AREA, torchvision bicubic, lerobot geometry, Qwen2-VL processor)"
"$here/run.sh" "$here/gr00t_vision_fixtures.py"
echo "== smolvla fixtures"
"$here/run.sh" "$here/smolvla_oracle.py" fixtures --out "$root/tests/fixtures/smolvla"
echo "== legacy (pre-0.4 layout) fixture, compared against upstream's migrated run"
"$here/run.sh" "$here/legacy_oracle.py" --out "$root/tests/fixtures/smolvla"
echo "== tokenizer Unicode coverage (reads the tokenizer fixtures and the smolvla cam1_stats checkpoint's vlm/)"
"$here/run.sh" "$here/unicode_fixtures.py"
echo "== real-time chunking fixture (reads the smolvla cam1_stats case)"
"$here/run.sh" "$here/rtc_oracle.py" --out "$root/tests/fixtures/smolvla_rtc"
echo "== pi0 / pi0.5 fixtures (the stand-in PaliGemma tokenizer's hub cache first)"
"$here/run.sh" "$here/pi_oracle.py" tokenizer
"$here/run.sh" "$here/pi_oracle.py" fixtures --family pi0
"$here/run.sh" "$here/pi_oracle.py" fixtures --family pi05
echo "== pi0 / pi0.5 real-time chunking fixtures (read the pi0 and pi05 cam2_bf16 and cam1_relative cases)"
"$here/run.sh" "$here/pi_rtc_oracle.py" --family pi0
"$here/run.sh" "$here/pi_rtc_oracle.py" --family pi05
"$here/run.sh" "$here/pi_rtc_oracle.py" --family pi0 --relative
"$here/run.sh" "$here/pi_rtc_oracle.py" --family pi05 --relative
echo "== FluxVLA pi0.5 run directories (read the pi05 cam1_quantiles_bins and variant_dims cases)"
"$here/run.sh" "$here/fluxvla_oracle.py" fixtures
"$here/run.sh" "$here/fluxvla_oracle.py" tokenizer
echo "== GR00T N1.7 fixtures (the stand-in Qwen3-VL backbone repository's hub cache first)"
"$here/run.sh" "$here/gr00t_oracle.py" hub --tiny-only
"$here/run.sh" "$here/gr00t_oracle.py" fixtures
"$here/run.sh" "$here/gr00t_rtc_oracle.py"  # GR00T N1.7 real-time chunking (reads the cam2_new case)
"$here/run.sh" "$here/gr00t_relative_oracle.py"  # GR00T N1.7 relative actions (the cam2_new weights and frames)
echo "== GR00T N1.6 fixtures (tiny raw checkpoint, stand-in Eagle directory, block and end-to-end oracles)"
"$here/run.sh" "$here/gr00t_n16_oracle.py"
"$here/run.sh" "$here/gr00t_n16_decode_oracle.py"  # GR00T N1.6 relative and mean/std actions (the gr00t_n16 weights and frames)
echo "== demo policy"
"$here/run.sh" "$here/smolvla_oracle.py" demo --out "$root/models/demo"
echo "== large fixtures into tests/fixtures/packed (git stores them compressed; the build expands them)"
python3 "$root/scripts/fixture_packs.py" pack
