#!/usr/bin/env bash
# Creates the oracle virtualenv (upstream lerobot/transformers/torch at exact pins) outside the repo.
# Idempotent: a stamp holding the hash of requirements.txt turns a re-run into a no-op.
#
#   TETHER_CACHE               cache root (default ~/.cache/tether)
#   TETHER_ORACLE_PYTHON       interpreter to use (skips the search)
#   TETHER_ORACLE_BUILD_PYTHON=1  ignore any interpreter on the machine and build CPython 3.13
#                              from Debian trixie's source package into $TETHER_CACHE/python3.13
set -euo pipefail

here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
cache="${TETHER_CACHE:-$HOME/.cache/tether}"
venv="$cache/oracle/venv"
req="$here/requirements.txt"
built_python_prefix="$cache/python3.13"
log() { echo "[oracle-setup] $*" >&2; }

python_ok() {  # lerobot 0.6.1 needs >= 3.12, with a working venv module
  "$1" -c 'import sys, venv, ensurepip; sys.exit(0 if sys.version_info >= (3, 12) else 1)' >/dev/null 2>&1
}

find_python() {
  local cand
  if [[ -n "${TETHER_ORACLE_PYTHON:-}" ]]; then
    python_ok "$TETHER_ORACLE_PYTHON" || { log "TETHER_ORACLE_PYTHON=$TETHER_ORACLE_PYTHON is not a usable python >= 3.12"; return 1; }
    echo "$TETHER_ORACLE_PYTHON"; return 0
  fi
  local cands=("$built_python_prefix/bin/python3.13")
  for cand in python3.13 python3.12 python3; do
    command -v "$cand" >/dev/null 2>&1 && cands+=("$(command -v "$cand")")
  done
  # pyenv shims refuse versions that are installed but not selected; look at the installs directly
  local pyenv_root="${PYENV_ROOT:-$HOME/.pyenv}"
  if [[ -d "$pyenv_root/versions" ]]; then
    for cand in $(ls -1 "$pyenv_root/versions" | grep -E '^3\.(1[2-9])\.[0-9]+$' | sort -V -r); do
      cands+=("$pyenv_root/versions/$cand/bin/python3")
    done
  fi
  for cand in "${cands[@]}"; do
    if [[ -x "$cand" ]] && python_ok "$cand"; then echo "$cand"; return 0; fi
  done
  return 1
}

debian_mirror() {  # the mirror this machine already uses for bookworm
  local uri=""
  if [[ -f /etc/apt/sources.list.d/debian.sources ]]; then
    uri="$(awk '/^URIs:/ && $2 ~ /debian\/?$/ && $2 !~ /security/ {print $2; exit}' /etc/apt/sources.list.d/debian.sources)"
  fi
  if [[ -z "$uri" && -f /etc/apt/sources.list ]]; then
    uri="$(awk '$1=="deb" && $3 ~ /^bookworm$/ {print $2; exit}' /etc/apt/sources.list)"
  fi
  echo "${uri:-http://deb.debian.org/debian}"
}

build_python() {
  local prefix="$built_python_prefix" work="$cache/python-build"
  log "building CPython 3.13 from Debian trixie sources into $prefix"
  local mirror; mirror="$(debian_mirror)"
  local src_list=/etc/apt/sources.list.d/tether-trixie-src.sources
  if [[ ! -f "$src_list" ]]; then
    # source entries only: no trixie binary package can be installed through this file; it is
    # removed again once the source is downloaded
    cat >"$src_list" <<EOF
Types: deb-src
URIs: $mirror
Suites: trixie
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
EOF
  fi
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
    build-essential dpkg-dev pkg-config libssl-dev zlib1g-dev libbz2-dev libffi-dev liblzma-dev \
    libsqlite3-dev libreadline-dev uuid-dev libgdbm-dev libgdbm-compat-dev libncursesw5-dev \
    libexpat1-dev >/dev/null
  rm -rf "$work" && mkdir -p "$work"
  (cd "$work" && apt-get source --download-only -qq python3.13)
  rm -f "$src_list"
  (cd "$work" && dpkg-source -x --skip-debianization --no-check "$(ls -1 python3.13_*.dsc | head -n1)" src >/dev/null)
  local tarball_dir="$work/src"
  [[ -x "$tarball_dir/configure" ]] || { log "python3.13 source did not unpack to $tarball_dir"; return 1; }
  (cd "$tarball_dir" && ./configure --prefix="$prefix" --with-ensurepip=install --with-system-expat \
      >"$work/configure.log" 2>&1 \
    && make -j2 >"$work/make.log" 2>&1 && make install >"$work/install.log" 2>&1)
  python_ok "$prefix/bin/python3.13" || { log "built interpreter at $prefix does not work; logs in $work"; return 1; }
  rm -rf "$tarball_dir"
  log "built $("$prefix/bin/python3.13" --version)"
}

if [[ "${TETHER_ORACLE_BUILD_PYTHON:-0}" == "1" ]]; then
  python_ok "$built_python_prefix/bin/python3.13" || build_python
  py="$built_python_prefix/bin/python3.13"
else
  py="$(find_python || true)"
  if [[ -z "$py" ]]; then
    build_python
    py="$built_python_prefix/bin/python3.13"
  fi
fi

stamp="$venv/.tether-stamp"
want="$(sha256sum "$req" | cut -d' ' -f1) $("$py" -c 'import sys; print(sys.version.split()[0])')"
if [[ -f "$stamp" && "$(cat "$stamp")" == "$want" && -x "$venv/bin/python" ]]; then
  exit 0
fi

log "creating $venv with $py"
rm -rf "$venv"
mkdir -p "$(dirname "$venv")"
"$py" -m venv "$venv"
"$venv/bin/python" -m pip install -q -r "$req"
"$venv/bin/python" -c 'import lerobot.policies.smolvla.modeling_smolvla, lerobot.policies.pi0.modeling_pi0, lerobot.policies.pi05.modeling_pi05, lerobot.policies.groot.groot_n1_7, transformers, torch, scipy, sentencepiece, diffusers, tree'
echo "$want" >"$stamp"
log "ready: $venv"
