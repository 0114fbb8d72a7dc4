#!/usr/bin/env bash
# Runs a script from tools/oracle/ (or any path) inside the oracle venv, fully offline.
# Usage: tools/oracle/run.sh <script.py> [args...]
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
cache="${TETHER_CACHE:-$HOME/.cache/tether}"
"$here/setup.sh"
# the scripts read and write fixtures as plain files: expand the packed ones (tests/fixtures/packed) first
python3 "$here/../../scripts/fixture_packs.py" unpack
script="$1"; shift
if [[ ! -f "$script" && -f "$here/$script" ]]; then script="$here/$script"; fi
# nothing may come from a hub: every model file the scripts need is written locally
export HF_HUB_OFFLINE=1 TRANSFORMERS_OFFLINE=1 HF_DATASETS_OFFLINE=1
export HF_HOME="$cache/oracle/hf-home" TOKENIZERS_PARALLELISM=false PYTHONHASHSEED=0
export PYTHONPATH="$here${PYTHONPATH:+:$PYTHONPATH}"
exec "$cache/oracle/venv/bin/python" "$script" "$@"
