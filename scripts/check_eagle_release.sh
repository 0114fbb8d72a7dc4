#!/usr/bin/env bash
# Checks Tether's GR00T N1.6 input side against a real Eagle directory, the one Isaac-GR00T vendors at
# gr00t/model/modules/nvidia/Eagle-Block2A-2B-v2 (not on the hub or PyPI, so no committed fixture can hold it).
# Usage: scripts/check_eagle_release.sh <Eagle-Block2A-2B-v2 directory>
#
# 1. tools/oracle/eagle_release_check.py runs that directory's own Eagle3_VLProcessor (trust_remote_code) as
#    Isaac-GR00T's N1.6 processor and collator call it, in the oracle venv with Isaac-GR00T's transformers pin
#    (4.51.3, with tokenizers 0.21, huggingface_hub 0.x, and av and lmdb, which the processor imports) put first on
#    PYTHONPATH from a cache directory. The remote code does not import under the oracle's transformers 5.
# 2. The test Gr00tN16EagleRelease.ProcessorAndTokenizerMatchTheRealDirectory compares Tether with what it wrote:
#    pixel values, prompt ids, and the tokenizer on the shared 1,773-string corpus.
# Exit status: the test's.
set -euo pipefail
cd "$(dirname "$0")/.."
[ $# -eq 1 ] && [ -d "$1" ] || { echo "usage: $0 <Eagle-Block2A-2B-v2 directory>" >&2; exit 2; }
eagle="$(cd "$1" && pwd)"
for f in config.json vocab.json merges.txt tokenizer_config.json processing_eagle3_vl.py; do
  [ -f "$eagle/$f" ] || { echo "error: $eagle has no $f (is it the Eagle-Block2A-2B-v2 directory?)" >&2; exit 2; }
done
cache="${TETHER_CACHE:-$HOME/.cache/tether}"
tools/oracle/setup.sh
deps="$cache/eagle-release-deps"
pins=("transformers==4.51.3" "tokenizers>=0.21,<0.22" "huggingface_hub>=0.30,<1.0" "av" "lmdb")
if [ ! -f "$deps/.installed" ] || [ "$(cat "$deps/.installed")" != "${pins[*]}" ]; then
  rm -rf "$deps"
  # --no-deps: everything else (torch, numpy, Pillow, safetensors) comes from the oracle venv.
  "$cache/oracle/venv/bin/python" -m pip install -q --no-deps --target "$deps" "${pins[@]}"
  echo "${pins[*]}" >"$deps/.installed"
fi
out="$(mktemp -d)"
trap 'rm -rf "$out"' EXIT
HF_HUB_OFFLINE=1 HF_HOME="$cache/oracle/hf-home" TOKENIZERS_PARALLELISM=false PYTHONPATH="$deps" \
  "$cache/oracle/venv/bin/python" tools/oracle/eagle_release_check.py --eagle-dir "$eagle" --out "$out"
[ -d build/release ] || scripts/setup.sh release >/dev/null
cmake --build build/release --target test_parity >/dev/null
TETHER_EAGLE_DIR="$eagle" TETHER_EAGLE_EXPECTED="$out" \
  ctest --test-dir build/release -R '^Gr00tN16EagleRelease\.' --output-on-failure -V |
  grep -E '^[0-9]+:   |Passed|Failed|Skipped'
