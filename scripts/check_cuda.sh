#!/usr/bin/env bash
# The CUDA backend's device check, in two halves.
#
#   scripts/check_cuda.sh --prepare [preset]
#                                     here (no GPU needed): builds the preset (cuda-check by default: machine code for sm_90a only) with the CUDA backend, packs the
#                                     binaries and the shared libraries a bare GPU machine lacks into .cuda-check/
#                                     (xz), and fails if the working tree and the bundle together would not fit the
#                                     device tool's 64 MiB.
#   scripts/check_cuda.sh             on the GPU machine, from the repository root, with .cuda-check carried: unpacks
#                                     the bundle and prints one table:
#     - probe: the GPU, driver and libraries (nvidia-smi, tether doctor);
#     - test_backend_ops on cuda against the float64 references (every op), and twice in a row compared bit for bit;
#     - compute-sanitizer memcheck and racecheck on the op tests, where the machine allows them;
#     - the parity suites of every family (SmolVLA, pi0, pi0.5, FluxVLA, GR00T N1.7 and N1.6) with TETHER_BACKEND=cuda;
#     - the demo policy's latency per stage on cuda and on the CPU (tether bench).
# Not in it yet (printed as "not run"): full-size random checkpoints generated on the device, the CUDA backend
# against the CPU backend on them, batch-8 throughput, and lerobot's PyTorch on the same GPU.
# Budget: the whole device half is meant to end in 8 minutes; each step has its own timeout.
set -uo pipefail
cd "$(dirname "$0")/.."
bundle=.cuda-check
limit_mib=64

if [ "${1:-}" = "--prepare" ]; then
  set -e
  preset="${2:-cuda-check}"
  scripts/setup.sh "$preset" tether test_backend test_parity test_policy
  grep -q '^TETHER_HAVE_CUDA_BUILD:INTERNAL=ON' "build/$preset/CMakeCache.txt" ||
    { echo "check_cuda --prepare: the $preset build has no CUDA backend (no nvcc 12.6+ found)" >&2; exit 1; }
  rm -rf "$bundle" && mkdir -p "$bundle/stage/bin" "$bundle/stage/lib"
  bins=("build/$preset/tether" "build/$preset/tests/backend/test_backend" "build/$preset/tests/policy/test_parity"
        "build/$preset/tests/policy/test_policy")
  for b in "${bins[@]}"; do strip -o "$bundle/stage/bin/$(basename "$b")" "$b"; done
  # Every shared library the binaries load, except the C library's own (the GPU machine's glibc is newer) and the
  # CUDA libraries, which the machine's CUDA image provides (cuBLASLt alone is 540 MB).
  ldd "${bins[@]}" | awk '/=> \//{print $3}' | sort -u |
    grep -vE '/(libc|libm|libdl|libpthread|librt|libresolv|ld-linux[^/]*)\.so|/libcublas|/libcudart' |
    while read -r lib; do cp -L "$lib" "$bundle/stage/lib/"; done
  strip --strip-unneeded "$bundle"/stage/lib/*.so* 2>/dev/null || true
  # Where the tests look for their fixtures (compiled in), so the device side can point that path at its copy.
  sed -n 's/^CMAKE_HOME_DIRECTORY:INTERNAL=//p' "build/$preset/CMakeCache.txt" >"$bundle/stage/source_dir"
  tar -C "$bundle/stage" -cf - . | xz -T2 -6 >"$bundle/bundle.tar.xz"
  rm -rf "$bundle/stage"
  tree_bytes=$(git ls-files -z | xargs -0 stat -c %s | awk '{s+=$1} END {print s}')
  bundle_bytes=$(stat -c %s "$bundle/bundle.tar.xz")
  total=$(((tree_bytes + bundle_bytes) / 1048576))
  printf 'check_cuda --prepare: working tree %d MiB + bundle %d MiB = %d MiB of the %d MiB the device tool carries\n' \
    $((tree_bytes / 1048576)) $((bundle_bytes / 1048576)) "$total" "$limit_mib"
  [ "$total" -lt "$limit_mib" ] || { echo "check_cuda --prepare: too large to carry" >&2; exit 1; }
  echo "check_cuda --prepare: run on the device: scripts/check_cuda.sh (carry .cuda-check)"
  exit 0
fi

# ---- the device half
[ -f "$bundle/bundle.tar.xz" ] || { echo "check_cuda: no $bundle/bundle.tar.xz: run scripts/check_cuda.sh --prepare here first" >&2; exit 2; }
work=$(mktemp -d)
tar -C "$work" -xJf "$bundle/bundle.tar.xz"
source_dir=$(cat "$work/source_dir")
# The test binaries read fixtures from the path they were built at; point it at this copy.
if [ "$source_dir" != "$PWD" ] && [ ! -e "$source_dir" ]; then mkdir -p "$(dirname "$source_dir")" && ln -s "$PWD" "$source_dir"; fi
cuda_libs=$(python3 - <<'PY' 2>/dev/null
import glob, os
try:
    import nvidia
    roots = list(nvidia.__path__)
except Exception:
    roots = []
print(":".join(sorted({os.path.dirname(p) for r in roots for p in glob.glob(r + "/**/libcublasLt.so*", recursive=True)})))
PY
)
export LD_LIBRARY_PATH="$work/lib:${cuda_libs}:/usr/local/cuda/lib64:${LD_LIBRARY_PATH:-}"
# Fixtures stored as xz packs in git are expanded here as the build expands them elsewhere (Python's lzma, no build).
if [ -f scripts/fixture_packs.py ]; then python3 scripts/fixture_packs.py unpack >/dev/null; fi
bin="$work/bin"
out="${OUT:-$work/out}"
mkdir -p "$out"
table="$out/check_cuda.txt"
printf '%-44s %-8s %s\n' step result detail | tee "$table"
row() { printf '%-44s %-8s %s\n' "$1" "$2" "$3" | tee -a "$table"; }
run_step() {  # name, timeout seconds, command...: ok on exit 0, the log's last line as detail
  local name=$1 limit=$2 log="$out/$(tr ' /' '__' <<<"$1").log"
  shift 2
  if timeout "$limit" "$@" >"$log" 2>&1; then row "$name" ok "$(tail -1 "$log" | cut -c1-90)"
  else row "$name" FAIL "exit $? ($(tail -1 "$log" | cut -c1-80)); log: $(basename "$log")"; fi
}

row "GPU" info "$(nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>&1 | head -1)"
run_step "tether doctor" 60 "$bin/tether" doctor
# Everything below needs the backend on this device: a skip would read as a pass, so a skipped op test ends the check.
gate=$("$bin/test_backend" --gtest_filter='*ConstantsReadAsUploaded/cuda' 2>&1)
if grep -q 'skipped:' <<<"$gate" || ! grep -q '\[  PASSED  \] 1 test' <<<"$gate"; then
  row "cuda backend usable" FAIL "$(grep -m1 'skipped:' <<<"$gate" | sed 's/.*skipped: //' | cut -c1-100)"
  echo "check_cuda: table in $table"
  exit 1
fi
row "cuda backend usable" ok "constants round-trip through the device"
run_step "op tests on cuda vs float64" 120 "$bin/test_backend" --gtest_filter='*BackendOps*/cuda'
run_step "op tests on cuda, second run" 120 "$bin/test_backend" --gtest_filter='*BackendOps*/cuda'
ops_rel() { grep -h 'rel|diff| ] cuda ' "$out"/op_tests_on_cuda*.log | sort | uniq | wc -l; }
if diff <(grep -h 'rel|diff| ] cuda ' "$out/op_tests_on_cuda_vs_float64.log") \
        <(grep -h 'rel|diff| ] cuda ' "$out/op_tests_on_cuda,_second_run.log") >/dev/null 2>&1; then
  row "op tests: two runs agree" ok "$(ops_rel) error figures identical"
else
  row "op tests: two runs agree" FAIL "the two runs' error figures differ"
fi
if command -v compute-sanitizer >/dev/null; then
  run_step "compute-sanitizer memcheck (op tests)" 180 compute-sanitizer --tool memcheck --error-exitcode 1 \
    "$bin/test_backend" --gtest_filter='*BackendOps*/cuda'
  run_step "compute-sanitizer racecheck (op tests)" 180 compute-sanitizer --tool racecheck --error-exitcode 1 \
    "$bin/test_backend" --gtest_filter='*BackendOps.Attention/cuda:*BackendOps.Norms/cuda'
else
  row "compute-sanitizer" "not run" "not on this machine"
fi
TETHER_BACKEND=cuda run_step "parity: SmolVLA, pi0, pi0.5, GR00T (cuda)" 240 "$bin/test_parity"
TETHER_BACKEND=cuda run_step "parity: FluxVLA (cuda)" 120 "$bin/test_policy" --gtest_filter='*Fluxvla*'
for backend in cuda cpu; do
  run_step "demo policy latency ($backend, 50 runs)" 120 "$bin/tether" bench models/demo/smolvla-demo \
    --backend "$backend" --iterations 50 --warmup 3
done
row "full-size SmolVLA / pi0 / GR00T N1.7" "not run" "not in this script yet"
row "lerobot PyTorch on the same GPU" "not run" "not in this script yet"
echo "check_cuda: table in $table"
! grep -q ' FAIL ' "$table"
