#!/usr/bin/env bash
# Creates .venv/ at the repository root with the pinned test tools and the client package (editable).
# Idempotent: a re-run is a no-op while the stamp (requirements + pyproject + interpreter) matches.
# Usage: scripts/python_env.sh            then: .venv/bin/python -m pytest python/tests
set -euo pipefail
cd "$(dirname "$0")/.."

python="${PYTHON:-python3}"
venv=.venv
stamp_file="$venv/.tether-stamp"

# What the environment depends on; a change to any of these rebuilds it.
stamp="$( { "$python" -c 'import sys; print(sys.version)'; cat "$0" python/requirements-test.txt python/requirements-test-nodeps.txt python/pyproject.toml; } \
  | sha256sum | cut -d' ' -f1)"
if [ -f "$stamp_file" ] && [ "$(cat "$stamp_file")" = "$stamp" ] && [ -x "$venv/bin/python" ]; then
  exit 0
fi

# Debian ships venv/ensurepip in a separate package.
if ! "$python" -c 'import venv, ensurepip' >/dev/null 2>&1; then
  echo "python_env: installing python3-venv"
  sudo=""
  [ "$(id -u)" -ne 0 ] && sudo="sudo"
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends python3-venv >/dev/null
fi

# A venv made by another interpreter (another Python version) is made anew.
if [ -x "$venv/bin/python" ] && [ "$("$venv/bin/python" -c 'import sys; print(sys.version)')" != "$("$python" -c 'import sys; print(sys.version)')" ]; then
  rm -rf "$venv"
fi
if [ ! -x "$venv/bin/python" ]; then
  "$python" -m venv "$venv"
fi
"$venv/bin/python" -m pip install -q --disable-pip-version-check -r python/requirements-test.txt
"$venv/bin/python" -m pip install -q --disable-pip-version-check --no-deps -r python/requirements-test-nodeps.txt
# No build isolation: the pinned setuptools above builds the editable install, so nothing else is fetched.
"$venv/bin/python" -m pip install -q --disable-pip-version-check --no-build-isolation --no-deps -e python/
echo "$stamp" >"$stamp_file"
echo "python_env: $venv ready ($("$venv/bin/python" --version))"
