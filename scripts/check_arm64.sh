#!/usr/bin/env bash
# Cross-builds Tether for aarch64 (Jetson Orin / Thor) into build/arm64 and runs the `unit` and `parity` tests
# under qemu-user-static. Installs what is missing first (Debian 12 amd64 + multiarch arm64; idempotent, quick when
# done). Slow under emulation, so not part of scripts/test.sh. Ends with one line starting PASS or FAIL.
# Usage: scripts/check_arm64.sh [extra ctest arguments]     env: JOBS (build and test jobs, default: nproc)
set -uo pipefail
cd "$(dirname "$0")/.."
start=$(date +%s)
jobs="${JOBS:-$(nproc)}"
sysroot=build/arm64-sysroot

elapsed() { local s=$(($(date +%s) - start)); printf '%dm%02ds' $((s / 60)) $((s % 60)); }
fail() {
  echo "check_arm64: $*" >&2
  echo "FAIL: aarch64 check ($*) after $(elapsed)"
  exit 1
}

sudo=""
[ "$(id -u)" -ne 0 ] && sudo="sudo"
installed() { dpkg-query -W -f='${Status}' "$1" 2>/dev/null | grep -q "install ok installed"; }

# Host tools. nlohmann-json3-dev and libcli11-dev are header-only Architecture: all packages, shared by both builds.
host_packages=(
  build-essential cmake ninja-build pkg-config python3 crossbuild-essential-arm64 qemu-user-static
  nlohmann-json3-dev libcli11-dev
)
# The target libraries, as in scripts/setup.sh. Not needed: OpenBLAS (only bench/, off here) and
# ocl-icd-opencl-dev (Debian builds arm64 oneDNN without the OpenCL GPU runtime, so its dnnl-config.cmake does not
# look for OpenCL). Two -dev packages are not co-installable with their amd64 twins and are handled below (their
# libraries are, and are installed here): libdnnl-dev (both ship /usr/include/oneapi/dnnl/dnnl_config.h, with
# different contents), libonig-dev and libsimdjson-dev (not Multi-Arch: same, so dpkg allows only one architecture of
# each).
arm64_packages=(
  libdnnl2 libonig5 libsimdjson14 libicu-dev libspng-dev libturbojpeg0-dev libboost1.81-dev
  libcurl4-openssl-dev libssl-dev libgtest-dev libgmock-dev libzmq3-dev cppzmq-dev
)
# The -dev packages unpacked into $sysroot: "dev-package runtime-package library-name". libmsgpuck-dev is not
# Multi-Arch either and has no runtime package (a static library): "-" takes the version of the installed amd64 twin.
sysroot_packages=("libdnnl-dev libdnnl2 libdnnl" "libonig-dev libonig5 libonig" "libsimdjson-dev libsimdjson14 libsimdjson"
  "libmsgpuck-dev - libmsgpuck")

need_update=0
if ! dpkg --print-foreign-architectures | grep -qx arm64; then
  echo "check_arm64: adding the arm64 architecture to dpkg"
  $sudo dpkg --add-architecture arm64 || fail "dpkg --add-architecture arm64 failed"
  need_update=1
fi
missing=()
for p in "${host_packages[@]}"; do installed "$p" || missing+=("$p"); done
for p in "${arm64_packages[@]}"; do installed "$p:arm64" || missing+=("$p:arm64"); done
if ((${#missing[@]})); then
  need_update=1
fi
if ((need_update)); then
  $sudo apt-get update -qq || fail "apt-get update failed"
fi
if ((${#missing[@]})); then
  # Multi-Arch: same packages must have one version on every architecture, so apt may upgrade an installed amd64
  # package to the version of its new arm64 twin; it must never remove one (the native build needs them all).
  sim=$(apt-get install -s --no-install-recommends "${missing[@]}" 2>&1) || fail "apt-get cannot install ${missing[*]}: $(tail -1 <<<"$sim")"
  if grep -q '^Remv' <<<"$sim"; then
    grep '^Remv' <<<"$sim" >&2
    fail "installing ${missing[*]} would remove the packages above; not installing"
  fi
  upgrades=$(grep -cE '^Inst [^ ]+ \[' <<<"$sim" || true)
  echo "check_arm64: installing ${missing[*]} (apt also upgrades $upgrades installed packages to matching versions)"
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null ||
    fail "apt-get install ${missing[*]} failed"
fi

# The -dev packages above (headers, CMake package or .pc file, the lib*.so link) go into a folder of their own,
# unpacked from their .debs at the version of the installed library, which the lib*.so links there point at. The
# arm64 preset puts $sysroot/usr on CMAKE_PREFIX_PATH, so find_package and pkg-config look there first. The .pc
# files name /usr; they are rewritten relative to their own folder. Redone whenever a library's version changes.
package_version() {  # dev-package runtime-package: the version to unpack
  if [ "$2" = "-" ]; then dpkg-query -W -f='${Version}' "$1"; else dpkg-query -W -f='${Version}' "$2:arm64"; fi
}
want=""
for entry in "${sysroot_packages[@]}"; do
  read -r dev lib _ <<<"$entry"
  want+="$dev=$(package_version "$dev" "$lib") "
done
stamp="$sysroot/.unpacked"
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  rm -rf "$sysroot" && mkdir -p "$sysroot/debs" || fail "cannot create $sysroot"
  for entry in "${sysroot_packages[@]}"; do
    read -r dev lib name <<<"$entry"
    version=$(package_version "$dev" "$lib")
    echo "check_arm64: unpacking $dev:arm64 $version into $sysroot"
    # An amd64 binNMU (version suffix +bN, a rebuild of the same source) may have no arm64 twin: take the plain
    # source version there.
    for v in "$version" "${version%+b[0-9]*}"; do
      (cd "$sysroot/debs" && apt-get download -q "$dev:arm64=$v" 2>&1 | grep -v '^W: Download is performed unsandboxed') ||
        true
      ls "$sysroot"/debs/"$dev"_*_arm64.deb >/dev/null 2>&1 && break
    done
    deb=$(ls "$sysroot"/debs/"$dev"_*_arm64.deb 2>/dev/null | head -1)
    [ -n "$deb" ] || fail "apt-get download $dev:arm64=$version failed"
    dpkg-deb -x "$deb" "$sysroot" || fail "dpkg-deb -x $deb failed"
    for f in /usr/lib/aarch64-linux-gnu/"$name".so.*; do
      [ -e "$f" ] && ln -sf "$f" "$sysroot/usr/lib/aarch64-linux-gnu/"
    done
  done
  for pc in "$sysroot"/usr/lib/aarch64-linux-gnu/pkgconfig/*.pc; do
    [ -f "$pc" ] || continue
    sed -i -e 's|^prefix=/usr$|prefix=${pcfiledir}/../../..|' -e 's#=/usr\([/ ]\|$\)#=${prefix}\1#' "$pc" ||
      fail "cannot rewrite $pc"
  done
  printf '%s' "$want" >"$stamp"
fi

# Always configured (quick once done), so a change to the preset reaches an existing build/arm64.
cmake --preset arm64 >/dev/null || fail "cmake --preset arm64 failed"
echo "check_arm64: building build/arm64 (-j$jobs)"
cmake --build --preset arm64 -- -j"$jobs" 2>&1 | grep -vE '^\[[0-9]+/[0-9]+\] (Building|Linking)'
((PIPESTATUS[0] == 0)) || fail "the arm64 build failed"

# Two emulated CPUs, one per Jetson generation: qemu 7.2's default ("max") has 512-bit SVE, which no Jetson has.
#   orin: cortex-a76, ARMv8.2-A with NEON, no SVE, no bf16 (Orin's Cortex-A78AE is not among qemu 7.2's models)
#   thor: max with 128-bit vectors, SVE2 and bf16 (Thor's Neoverse V3AE)
cpus=("orin=cortex-a76" "thor=max,sve-default-vector-length=16")
counts=()
for entry in "${cpus[@]}"; do
  name=${entry%%=*}
  cpu=${entry#*=}
  log=build/arm64-check-$name.log
  echo "check_arm64: unit and parity tests under qemu-aarch64-static, CPU $cpu ($name-like; -j$jobs; slow)"
  QEMU_CPU=$cpu ctest --preset arm64 -j"$jobs" "$@" 2>&1 | tee "$log"
  rc=${PIPESTATUS[0]}
  summary=$(grep -E 'tests passed, [0-9]+ tests failed out of [0-9]+' "$log" | tail -1)
  [ -n "$summary" ] || fail "ctest ran no tests on $name (rc $rc; see $log)"
  total=$(sed -E 's/.* out of ([0-9]+).*/\1/' <<<"$summary")
  failed=$(sed -E 's/.*passed, ([0-9]+) tests failed.*/\1/' <<<"$summary")
  ((rc == 0)) || fail "$failed of $total unit+parity tests failed on the $name-like CPU $cpu (see $log)"
  counts+=("$total on $name ($cpu)")
done
summary_line=$(printf '%s; ' "${counts[@]}")
echo "PASS: aarch64 cross-build; unit+parity tests passed under qemu-aarch64-static: ${summary_line%; } in $(elapsed)"
