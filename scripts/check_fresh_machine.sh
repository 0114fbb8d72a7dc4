#!/usr/bin/env bash
# Proves that the README's two commands work on a fresh Debian 12 machine: debootstraps a minimal bookworm
# (`--variant=minbase`, cached), puts a clean clone of this repository's HEAD in it and runs, as root in the
# clone, `./scripts/demo.sh --once` then `CI=true ./scripts/test.sh` (what .ci/run does), so a package that
# only the developer's machine has shows up as a set-up failure.
#
# Only committed work is checked: the chroot gets `git clone` of HEAD; uncommitted changes are NOT included.
# Not part of the default tests (it takes long: apt installs, two full builds on this machine's cores, the suite).
#
# Usage: scripts/check_fresh_machine.sh [--rebuild-base]     (as root; installs debootstrap when missing)
#   TETHER_FRESH_DIR     where the cached base, the chroot and the logs live (default /var/cache/tether-fresh;
#                        must be outside the repository)
#   TETHER_FRESH_MIRROR  the Debian mirror (default: the one the host's apt sources use)
# Network: the chroot reaches only what the host reaches: the host's Debian mirror (same suites: bookworm and,
# where the host uses them, bookworm-updates / bookworm-security), and PyPI the way the host does (its
# resolv.conf, pip configuration, proxy and CA variables, and its locally added CA certificates).
# Ends with one line, `PASS (N min)` or `FAIL: <first error line> (log: FILE)`; exit code 0 or 1.
set -euo pipefail

suite=bookworm
arch="$(dpkg --print-architecture)"
script_dir="$(cd "$(dirname "$0")" && pwd)"
repo="$(git -C "$script_dir" rev-parse --show-toplevel)"
sha="$(git -C "$repo" rev-parse HEAD)"
dir="${TETHER_FRESH_DIR:-/var/cache/tether-fresh}"
rebuild_base=0
[ "${1:-}" = "--rebuild-base" ] && rebuild_base=1

die() { echo "FAIL: $*"; exit 1; }
[ "$(id -u)" -eq 0 ] || die "must run as root (debootstrap, chroot, mounts)"
mkdir -p "$dir"
dir="$(cd "$dir" && pwd -P)"
case "$dir/" in "$(cd "$repo" && pwd -P)/"*) die "TETHER_FRESH_DIR ($dir) must be outside the repository" ;; esac

exec 9>"$dir/lock"
flock -n 9 || die "another check_fresh_machine.sh is running on $dir"

base_tar="$dir/base-$suite-$arch-minbase.tar"
root="$dir/root"
mkdir -p "$dir/logs"
log="$dir/logs/$(date +%Y%m%d-%H%M%S)-${sha:0:12}.log"
: >"$log"
start=$(date +%s)

say() { echo "check_fresh_machine: $*" | tee -a "$log" >&2; }
minutes() { echo $(( ($(date +%s) - $1 + 30) / 60 )); }

# ---- mounts: everything under a chroot tree is unmounted on exit, and a tree is only deleted with none left
mounts_under() { awk -v p="$1/" 'index($2 "/", p) == 1 { print $2 }' /proc/self/mounts | sort -r; }
unmount_under() {
  local m
  for m in $(mounts_under "$1"); do umount "$m" 2>/dev/null || umount -l "$m" 2>/dev/null || true; done
  [ -z "$(mounts_under "$1")" ]
}
remove_tree() {
  [ -e "$1" ] || return 0
  unmount_under "$1" || die "cannot unmount what is mounted under $1; not deleting it"
  rm -rf --one-file-system "$1"
}
# Processes still running inside a tree (a step that was interrupted), by their ids.
stop_inside() {
  local p pids=()
  for p in /proc/[0-9]*; do
    [ "$(readlink "$p/root" 2>/dev/null)" = "$1" ] && pids+=("${p#/proc/}")
  done
  ((${#pids[@]})) || return 0
  kill -TERM "${pids[@]}" 2>/dev/null || true
  sleep 2
  kill -KILL "${pids[@]}" 2>/dev/null || true
}
step_pid=""
cleanup() {
  set +e
  if [ -n "$step_pid" ]; then kill -TERM -- "-$step_pid" 2>/dev/null; wait "$step_pid" 2>/dev/null; fi
  stop_inside "$root"
  unmount_under "$root" || true
  unmount_under "$dir/base.tmp" || true
}
trap cleanup EXIT
trap 'echo "FAIL: interrupted (log: $log)"; exit 1' INT TERM

# The first line of the log (from line $1 on) that reports an error (apt, CMake, compiler, ninja, CTest, pytest,
# pip, a shell); else the first that looks like one; else the last non-empty line.
first_error() {
  local line
  line="$(tail -n +"$1" "$log" | grep -E -m1 \
    '(^E: |CMake Error|(^|[^A-Za-z])error:|^FAILED|\*\*\*Failed|\*\*\*Exception|\*\*\*Timeout|\[  FAILED  \]|Traceback|^ERROR|^fatal:|No such file or directory|command not found)' || true)"
  [ -n "$line" ] || line="$(tail -n +"$1" "$log" | grep -v -E '(Passed|OK \]|(^|[^0-9])0 (tests )?failed)' \
    | grep -E -m1 '([Ee]rror|ERROR|FAIL|[Ff]ailed|[Nn]ot found|[Cc]annot |[Cc]ould not)' || true)"
  [ -n "$line" ] || line="$(tail -n +"$1" "$log" | grep -v '^\s*$' | tail -n 1 || true)"
  echo "${line:-no output}"
}
fail() { echo "FAIL: $(first_error "$1") (after $(minutes "$start") min; full log: $log)"; exit 1; }

# ---- the host's Debian mirror, from its apt sources (one-line .list and deb822 .sources files)
host_sources() {
  local f
  for f in /etc/apt/sources.list /etc/apt/sources.list.d/*.list; do
    [ -f "$f" ] || continue
    sed -e 's/#.*//' -e 's/\[[^]]*\]//' "$f" | awk '$1 == "deb" && NF >= 4 { c = $4; for (i = 5; i <= NF; i++) c = c " " $i; print $2, $3, c }'
  done
  for f in /etc/apt/sources.list.d/*.sources; do
    [ -f "$f" ] || continue
    awk '
      function flush(  nu, ns, u, s, i, j, t, deb) {
        deb = 0; nt = split(types, t, " "); for (i = 1; i <= nt; i++) if (t[i] == "deb") deb = 1
        if (deb && tolower(enabled) != "no") {
          nu = split(uris, u, " "); ns = split(suites, s, " ")
          for (i = 1; i <= nu; i++) for (j = 1; j <= ns; j++) print u[i], s[j], comps
        }
        types = uris = suites = comps = enabled = ""
      }
      /^[ \t]*#/ { next }
      /^[ \t]*$/ { flush(); next }
      /^[A-Za-z-]+:/ { key = tolower($1); sub(/^[^:]*:[ \t]*/, ""); val = $0 }
      /^[ \t]+/ { val = $0 }
      { gsub(/^[ \t]+|[ \t]+$/, "", val) }
      key == "types:" { types = types " " val } key == "uris:" { uris = uris " " val }
      key == "suites:" { suites = suites " " val } key == "components:" { comps = comps " " val }
      key == "enabled:" { enabled = val }
      END { flush() }' "$f" | sed 's/  */ /g'
  done
}
# Keep the Debian suites of this release (bookworm, bookworm-updates, bookworm-security, ...); third-party
# repositories (other suite names) are not part of a fresh machine.
mapfile -t sources < <(host_sources | awk -v s="$suite" '$2 == s || index($2, s "-") == 1' | sort -u)
mirror="${TETHER_FRESH_MIRROR:-}"
if [ -z "$mirror" ]; then
  mirror="$(printf '%s\n' "${sources[@]}" | awk -v s="$suite" '$2 == s { print $1; exit }')"
fi
[ -n "$mirror" ] || die "no '$suite' Debian mirror in the host's apt sources; set TETHER_FRESH_MIRROR"
if [ -n "${TETHER_FRESH_MIRROR:-}" ] || ! printf '%s\n' "${sources[@]}" | grep -q .; then
  sources=("$mirror $suite main")
fi

dirty="$(git -C "$repo" status --porcelain --untracked-files=no | wc -l)"
say "checking HEAD ${sha:0:12} of $repo (a clean clone; $dirty uncommitted change(s) NOT included)"
say "mirror $mirror; chroot sources: $(printf '%s; ' "${sources[@]}")"
say "log: $log"

# ---- the cached base: debootstrap once, keep a tarball; each run starts from a pristine copy of it
key="$suite $arch minbase $mirror"
if [ "$rebuild_base" = 1 ] || [ ! -f "$base_tar" ] || [ "$(cat "$base_tar.key" 2>/dev/null)" != "$key" ]; then
  if ! command -v debootstrap >/dev/null; then
    say "installing debootstrap on the host"
    { apt-get -o DPkg::Lock::Timeout=600 update -qq &&
      DEBIAN_FRONTEND=noninteractive apt-get -o DPkg::Lock::Timeout=600 install -y -qq --no-install-recommends debootstrap; } \
      >>"$log" 2>&1 || fail 1
  fi
  say "debootstrap --variant=minbase $suite (first run only; cached in $base_tar)"
  remove_tree "$dir/base.tmp"
  t0=$(date +%s)
  line=$(($(wc -l <"$log") + 1))
  debootstrap --variant=minbase --arch="$arch" "$suite" "$dir/base.tmp" "$mirror" >>"$log" 2>&1 || fail "$line"
  unmount_under "$dir/base.tmp" || die "debootstrap left mounts under $dir/base.tmp"
  tar -C "$dir/base.tmp" --numeric-owner -cpf "$base_tar.tmp" . && mv "$base_tar.tmp" "$base_tar"
  echo "$key" >"$base_tar.key"
  remove_tree "$dir/base.tmp"
  say "base ready ($(minutes "$t0") min, $(du -h "$base_tar" | cut -f1))"
fi

say "fresh chroot from the cached base: $root"
remove_tree "$root"
mkdir -p "$root"
tar -C "$root" --numeric-owner -xpf "$base_tar"

# What any installed Debian has and debootstrap leaves out: a hosts file (localhost) and a hostname.
[ -s "$root/etc/hosts" ] || printf '127.0.0.1\tlocalhost\n::1\t\tlocalhost ip6-localhost ip6-loopback\n' >"$root/etc/hosts"
[ -s "$root/etc/hostname" ] || echo tether-fresh >"$root/etc/hostname"

# apt: the host's Debian mirror and suites, and the host's settings for reaching it (proxy, date checks).
rm -f "$root"/etc/apt/sources.list.d/*
printf 'deb %s\n' "${sources[@]}" >"$root/etc/apt/sources.list"
grep -h -E '^[[:space:]]*Acquire::(https?::Proxy|Check-Valid-Until|Check-Date)' \
  /etc/apt/apt.conf /etc/apt/apt.conf.d/* 2>/dev/null >"$root/etc/apt/apt.conf.d/99host-mirror" || true
# PyPI: the host's resolver, pip configuration, local find-links folders and locally added CA certificates
# (a TLS-inspecting proxy's CA, for instance; the ca-certificates package puts them in the system bundle).
cp -L /etc/resolv.conf "$root/etc/resolv.conf"
for f in /etc/pip.conf /etc/xdg/pip/pip.conf "$HOME/.config/pip/pip.conf" "$HOME/.pip/pip.conf"; do
  [ -f "$f" ] || continue
  t="$root${f/#$HOME//root}"
  mkdir -p "$(dirname "$t")" && cp "$f" "$t"
done
if [ -d /usr/local/share/ca-certificates ]; then
  mkdir -p "$root/usr/local/share/ca-certificates"
  cp -a /usr/local/share/ca-certificates/. "$root/usr/local/share/ca-certificates/"
fi
for d in ${PIP_FIND_LINKS:-}; do
  case "$d" in /*) [ -d "$d" ] && mkdir -p "$root$d" && cp -a "$d/." "$root$d/" ;; esac
done
passenv=()
while IFS= read -r v; do passenv+=("$v"); done < <(env | grep -E \
  '^(PIP_[A-Z_]*|https?_proxy|HTTPS?_PROXY|no_proxy|NO_PROXY|all_proxy|ALL_PROXY|REQUESTS_CA_BUNDLE|SSL_CERT_FILE|SSL_CERT_DIR|CURL_CA_BUNDLE)=' || true)

# The clean clone of HEAD, where a new user would put it.
clone=/root/tether
git clone --quiet --no-hardlinks --no-checkout "$repo" "$root$clone" >>"$log" 2>&1
git -C "$root$clone" cat-file -e "$sha^{commit}" 2>/dev/null || git -C "$root$clone" fetch --quiet "$repo" "$sha" >>"$log" 2>&1
git -C "$root$clone" -c advice.detachedHead=false checkout --quiet --detach "$sha" >>"$log" 2>&1

mount -t proc proc "$root/proc"
mount --bind /sys "$root/sys"
mount --bind /dev "$root/dev"
mount --bind /dev/pts "$root/dev/pts"
mount -t tmpfs -o mode=1777,nosuid,nodev shm "$root/dev/shm"

# One README command, as root in the clone, in a login shell with a fresh machine's environment.
run_step() {
  local name="$1" cmd="$2" t0 line
  t0=$(date +%s)
  line=$(($(wc -l <"$log") + 1))
  say "\$ $cmd"
  echo "==== $name: $cmd" >>"$log"
  # In its own process group, in the background: a signal to this script stops the step and unmounts at once.
  setsid chroot "$root" /usr/bin/env -i HOME=/root USER=root LOGNAME=root SHELL=/bin/bash TERM=dumb \
    PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin "${passenv[@]}" \
    /bin/bash -lc "cd $clone && $cmd" </dev/null >>"$log" 2>&1 &
  step_pid=$!
  if ! wait "$step_pid"; then
    step_pid=""
    say "$name failed after $(minutes "$t0") min"
    fail "$line"
  fi
  step_pid=""
  say "$name passed ($(minutes "$t0") min)"
}
run_step demo "./scripts/demo.sh --once"
run_step test "CI=true ./scripts/test.sh"

cleanup
echo "PASS ($(minutes "$start") min)" | tee -a "$log"
