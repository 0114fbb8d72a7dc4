#!/usr/bin/env bash
# Builds Tether (installing what is missing) and runs the bundled demo policy on the sample image.
# The demo checkpoint has RANDOM weights: it shows the pipeline, not a trained behaviour.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh release
exec build/release/tether predict models/demo/smolvla-demo \
  --image front=models/demo/sample.png \
  --state 0,90,90,45,0,20 \
  --instruction "pick up the red cube and put it in the blue bowl" \
  --seed 7 "$@"
