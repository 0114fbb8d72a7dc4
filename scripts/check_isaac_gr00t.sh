#!/usr/bin/env bash
# Checks Tether's GR00T N1.6 against Isaac-GR00T's own code, from a checkout of it (Isaac-GR00T is not on PyPI, and
# its vendored Eagle directory gr00t/model/modules/nvidia/Eagle-Block2A-2B-v2 is not on the hub, so no committed
# fixture can come from either).
# Usage: scripts/check_isaac_gr00t.sh <Isaac-GR00T checkout>
#
# 1. tools/oracle/isaac_state_action_check.py runs Isaac-GR00T's StateActionProcessor on every committed N1.6 case
#    (tests/fixtures/gr00t_n16, gr00t_n16_decode): state encoding and action decoding, relative and mean/std actions
#    included, must equal what the fixtures hold (and Tether matches in the parity tests).
# 2. tools/oracle/eagle_release_check.py runs the Eagle directory's own Eagle3_VLProcessor (trust_remote_code) as
#    Isaac-GR00T's N1.6 processor and collator call it, under Isaac-GR00T's transformers pin (4.51.3, with
#    tokenizers 0.21, huggingface_hub 0.x, and av and lmdb, which the processor imports) put first on PYTHONPATH from
#    a cache directory: the remote code does not import under the oracle's transformers 5. The test
#    Gr00tN16EagleRelease.ProcessorAndTokenizerMatchTheRealDirectory then compares Tether with what it wrote: pixel
#    values, prompt ids, and the tokenizer on the shared 1,773-string corpus.
# 3. python/tests/test_isaac_gr00t_client.py runs Isaac-GR00T's own PolicyClient (gr00t/policy/server_client.py,
#    imported from the checkout) against `tether serve --gr00t-port` on the N1.6 decode fixture's two embodiments:
#    the modality config decoded into its ModalityConfig / ActionConfig classes, get_action from the layout its
#    open-loop evaluation sends, reset, ping, a wrong token and a bad observation.
# Exit status: non-zero when any check fails.
set -euo pipefail
cd "$(dirname "$0")/.."
[ $# -eq 1 ] && [ -d "$1" ] || { echo "usage: $0 <Isaac-GR00T checkout>" >&2; exit 2; }
isaac="$(cd "$1" && pwd)"
eagle="$isaac/gr00t/model/modules/nvidia/Eagle-Block2A-2B-v2"
for f in "$isaac/gr00t/data/state_action/state_action_processor.py" "$eagle/config.json" "$eagle/vocab.json" \
  "$eagle/merges.txt"; do
  [ -f "$f" ] || { echo "error: no $f (is $isaac an Isaac-GR00T checkout with N1.6?)" >&2; exit 2; }
done
cache="${TETHER_CACHE:-$HOME/.cache/tether}"
tools/oracle/setup.sh
python="$cache/oracle/venv/bin/python"

echo "== Isaac-GR00T's StateActionProcessor on the N1.6 fixtures"
python3 scripts/fixture_packs.py unpack  # the large fixtures are packed in git
"$python" tools/oracle/isaac_state_action_check.py --isaac "$isaac"

echo "== the Eagle directory's own processor against Tether"
deps="$cache/eagle-release-deps"
pins=("transformers==4.51.3" "tokenizers>=0.21,<0.22" "huggingface_hub>=0.30,<1.0" "av" "lmdb")
if [ ! -f "$deps/.installed" ] || [ "$(cat "$deps/.installed")" != "${pins[*]}" ]; then
  rm -rf "$deps"
  # --no-deps: everything else (torch, numpy, Pillow, safetensors) comes from the oracle venv.
  "$python" -m pip install -q --no-deps --target "$deps" "${pins[@]}"
  echo "${pins[*]}" >"$deps/.installed"
fi
out="$(mktemp -d)"
trap 'rm -rf "$out"' EXIT
HF_HUB_OFFLINE=1 HF_HOME="$cache/oracle/hf-home" TOKENIZERS_PARALLELISM=false PYTHONPATH="$deps" \
  "$python" tools/oracle/eagle_release_check.py --eagle-dir "$eagle" --out "$out"
[ -d build/release ] || scripts/setup.sh release >/dev/null
cmake --build build/release --target test_parity >/dev/null
TETHER_EAGLE_DIR="$eagle" TETHER_EAGLE_EXPECTED="$out" \
  ctest --test-dir build/release -R '^Gr00tN16EagleRelease\.' --output-on-failure -V |
  grep -E '^[0-9]+:   |Passed|Failed|Skipped'

echo "== Isaac-GR00T's PolicyClient against tether serve"
cmake --build build/release --target tether >/dev/null
scripts/python_env.sh >/dev/null
TETHER_ISAAC_GR00T="$isaac" .venv/bin/python -m pytest -q python/tests/test_isaac_gr00t_client.py
