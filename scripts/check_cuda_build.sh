#!/usr/bin/env bash
# What CI can prove about the CUDA backend without a GPU, read from the machine code the build produced:
#   - every GPU target listed in cmake/cuda.cmake has machine code, and the newest has PTX too;
#   - the hot kernels (kernels.cu, attention.cu) use no local memory and no stack (so no register spills: the build's
#     ptxas flags fail on spills as well, with warnings as errors);
#   - the float32 kernels hold no tensor-core instruction (HMMA / HGMMA / IMMA): fp32 is the parity mode, true
#     float32 arithmetic throughout.
# Prints one table; exits non-zero when a check fails. A build without the CUDA backend (no nvcc) is skipped with
# one line. Usage: scripts/check_cuda_build.sh [preset]   (default: release; scripts/test.sh passes its own)
set -euo pipefail
cd "$(dirname "$0")/.."
preset="${1:-release}"
build="build/$preset"
cache="$build/CMakeCache.txt"
[ -f "$cache" ] || { echo "check_cuda_build: $build is not configured (run scripts/setup.sh $preset)" >&2; exit 2; }
if ! grep -q '^TETHER_HAVE_CUDA_BUILD:INTERNAL=ON' "$cache"; then
  echo "check_cuda_build: skipped: this build has no CUDA backend (CMake found no nvcc 12.6+)"
  exit 0
fi

# cuobjdump (and the nvdisasm it disassembles with) from PyPI, pinned, installed once into the cache.
tools="${TETHER_CACHE:-$HOME/.cache/tether}/cuda-tools"
stamp="$tools/.stamp-$(sha256sum scripts/cuda_tools.txt | cut -c1-16)"
if [ ! -f "$stamp" ]; then
  rm -rf "$tools"
  PIP_ROOT_USER_ACTION=ignore python3 -m pip install -q --disable-pip-version-check --no-deps --target "$tools" \
    -r scripts/cuda_tools.txt
  touch "$stamp"
fi
cuobjdump=$(find "$tools" -path '*/bin/cuobjdump' | head -1)
[ -x "$cuobjdump" ] || chmod +x "$cuobjdump"

archs=$(sed -n 's/^TETHER_CUDA_ARCHS:STRING=//p' "$cache" | tr ';' ' ')
newest=$(awk '{print $NF}' <<<"$archs" | sed 's/a$//')
failed=0
row() { printf '%-38s %-6s %s\n' "$1" "$2" "$3"; [ "$2" = ok ] || failed=1; }

printf '%-38s %-6s %s\n' "check" "result" "detail"
objects=$(find "$build" -path '*tether_backend.dir*' -name '*.cu.o' | sort)
[ -n "$objects" ] || { row "CUDA objects" fail "no .cu.o under $build"; exit 1; }
for obj in $objects; do
  name=$(basename "$obj" .cu.o)
  have=$("$cuobjdump" --list-elf "$obj" 2>/dev/null | sed -n 's/.*\.sm_\([0-9a]*\)\.cubin$/\1/p' | sort -n | xargs)
  missing=""
  for a in $archs; do grep -qw "$a" <<<"$have" || missing+=" sm_$a"; done
  if [ -z "$missing" ]; then row "$name: machine code" ok "$(sed 's/[^ ]*/sm_&/g' <<<"$have")"; else row "$name: machine code" fail "missing$missing"; fi
  if "$cuobjdump" --list-ptx "$obj" 2>/dev/null | grep -q "sm_$newest\.ptx"; then
    row "$name: PTX for newer GPUs" ok "compute_$newest"
  else
    row "$name: PTX for newer GPUs" fail "no compute_$newest PTX"
  fi
  usage=$("$cuobjdump" --dump-resource-usage "$obj" 2>/dev/null)
  kernels=$(grep -c '^ Function' <<<"$usage" || true)
  heavy=$(grep -cE 'STACK:[1-9]|LOCAL:[1-9]' <<<"$usage" || true)
  if [ "$name" = angles ]; then
    # sin / cos / pow of arbitrary arguments reduce huge ones through a small stack array (cold kernels).
    row "$name: local memory" ok "$kernels kernel builds, $heavy with a stack frame (allowed: sin/cos/pow reduction)"
  elif [ "$heavy" -eq 0 ]; then
    row "$name: no spills, no local memory" ok "$kernels kernel builds, every one STACK:0 LOCAL:0"
  else
    row "$name: no spills, no local memory" fail "$heavy of $kernels kernel builds use local memory or stack"
  fi
  for a in 90a 87; do
    grep -qw "$a" <<<"$archs" || continue
    sass=$("$cuobjdump" -sass -arch "sm_$a" "$obj" 2>/dev/null || true)
    tensor=$(grep -cE '\b(HMMA|HGMMA|IMMA|QGMMA)\b' <<<"$sass" || true)
    ffma=$(grep -cE '\bFFMA\b' <<<"$sass" || true)
    if [ "$tensor" -eq 0 ]; then
      row "$name sm_$a: fp32 only" ok "no tensor-core instruction, $ffma FFMA"
    else
      row "$name sm_$a: fp32 only" fail "$tensor tensor-core instructions in float32 kernels"
    fi
  done
done
[ "$failed" -eq 0 ] || { echo "check_cuda_build: FAILED" >&2; exit 1; }
echo "check_cuda_build: every check passed (built for $(sed -n 's/^TETHER_CUDA_TARGETS_TEXT:INTERNAL=//p' "$cache"))"
