#!/usr/bin/env bash
# Repository hygiene, run by CTest (label unit): every C++ source file opens with a comment line on its purpose,
# model code never names the CPU backend's kernels (it goes through backend/backend.h), and every relative link in
# the README and docs/ resolves.
set -euo pipefail
cd "$(dirname "$0")/.."
status=0
while IFS= read -r f; do
  if ! head -1 "$f" | grep -q '^//'; then
    echo "$f: the first line is not a comment saying what the file is for"
    status=1
  fi
done < <(git ls-files 'src/*.cpp' 'src/*.h' 'tests/*.cpp' 'tests/*.h' 'bench/*.cpp' 'fuzz/*.cpp')
# The backend seam: models see the interface only.
if grep -rn --include='*.cpp' --include='*.h' -E '#include "backend/cpu/(kernels|gemm|attention|panel_gemm)' src/models; then
  echo "src/models includes CPU kernels directly: call the backend interface instead"
  status=1
fi
python3 scripts/check_doc_links.py README.md docs/*.md docs/*/*.md || status=1
exit $status
