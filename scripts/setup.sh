#!/usr/bin/env bash
# Installs what the build needs (Debian 12 packages) and builds Tether. Idempotent: quick when already done.
# Usage: scripts/setup.sh [preset [target...]]   (preset: release (default), ci, debug, asan; targets: all by
# default, e.g. `tether` alone for the demo)
set -euo pipefail
cd "$(dirname "$0")/.."
preset="${1:-release}"
targets=("${@:2}")

packages=(
  build-essential cmake ninja-build pkg-config git curl python3
  libopenblas-openmp-dev libdnnl-dev
  # Debian's dnnl-config.cmake calls find_package(OpenCL REQUIRED) (libdnnl is built with the OpenCL GPU runtime);
  # the package is only a Recommends of libdnnl-dev, which --no-install-recommends skips.
  ocl-icd-opencl-dev
  nlohmann-json3-dev libcli11-dev libsimdjson-dev
  libonig-dev libicu-dev libspng-dev libturbojpeg0-dev libboost1.81-dev
  libcurl4-openssl-dev libssl-dev
  libmsgpuck-dev libzmq3-dev cppzmq-dev
  libgtest-dev libgmock-dev libbenchmark-dev
)
missing=()
for p in "${packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ((${#missing[@]})); then
  echo "setup: installing ${missing[*]}"
  sudo=""
  [ "$(id -u)" -ne 0 ] && sudo="sudo"
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

# A build folder configured when -march=native was the default is reconfigured for the portable baseline.
if [ ! -f "build/$preset/build.ninja" ] || grep -q '^TETHER_NATIVE:BOOL=ON' "build/$preset/CMakeCache.txt" 2>/dev/null; then
  cmake --preset "$preset" -DTETHER_NATIVE=OFF >/dev/null
fi
# Progress lines are filtered out; the build's own exit status decides (a failed build never passes as done).
set +e
cmake --build --preset "$preset" ${targets[@]+--target "${targets[@]}"} -- -j"$(nproc)" 2>&1 |
  grep -vE '^\[[0-9]+/[0-9]+\] (Building|Linking)'
status=${PIPESTATUS[0]}
set -e
[ "$status" -eq 0 ] || { echo "setup: the $preset build failed (exit $status)" >&2; exit 1; }
test -x "build/$preset/tether"
