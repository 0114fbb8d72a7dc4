#!/usr/bin/env bash
# Builds Tether (installing what is missing) and runs the bundled demo policy on the sample image.
# The demo checkpoint has RANDOM weights: it shows the pipeline, not a trained behaviour.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh release
exec build/release/tether predict models/demo/smolvla-demo \
  --image front=models/demo/sample.png \
  --state=0.0,-0.5,0.8,0.1,0.0,0.3 \
  --instruction "pick up the red cube and place it in the bowl" \
  --seed 7 "$@"
