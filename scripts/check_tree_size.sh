#!/usr/bin/env bash
# Fails when the files git tracks add up to more than the limit (default 40 MiB; TETHER_TREE_LIMIT_MIB overrides),
# and then names the largest. Run by CTest (label unit). Sizes are those of the working tree's entries as a copy of
# the tree transfers them: a symlink counts as the link itself, not its target. Large oracle fixtures belong in the
# packs of tests/fixtures/packed (scripts/fixture_packs.py), not as plain tracked files.
set -euo pipefail
cd "$(dirname "$0")/.."
limit_mib="${TETHER_TREE_LIMIT_MIB:-40}"
limit=$((limit_mib * 1024 * 1024))
# A tracked path deleted in the working tree (not yet committed) has no size to count.
sizes="$(git ls-files -z | xargs -0 stat -c '%s %n' 2>/dev/null | sort -rn || true)"
total="$(awk '{ s += $1 } END { print s + 0 }' <<<"$sizes")"
files="$(wc -l <<<"$sizes")"
printf 'tracked files: %d, %.2f MiB (limit %d MiB)\n' "$files" "$(awk -v t="$total" 'BEGIN { print t / 1048576 }')" \
  "$limit_mib"
if [ "$total" -gt "$limit" ]; then
  echo "over the limit; the largest tracked files:"
  head -20 <<<"$sizes" | awk '{ size = $1; $1 = ""; printf "  %10d %s\n", size, substr($0, 2) }'
  exit 1
fi
