#!/usr/bin/env bash
# Run `dvc repro` on the every-method tiny preset (tests/support/tiny_params.py: TINY_ALL) in a fresh
# git + DVC copy of a commit, then print the digests of its data/ (benchmarks/artifact_digest.py).
# Compare two commits' digests to show a refactor changed no artifact:
#   bash benchmarks/tiny_repro.sh HEAD~5 > before.txt; bash benchmarks/tiny_repro.sh HEAD > after.txt
#   diff before.txt after.txt
# Usage: tiny_repro.sh [REF] [WORKDIR]   (REF default HEAD; the tiny preset is read from the
# checkout of this script, so both sides run the same params). Runs with the current
# environment's python and dvc (source .venv/bin/activate first) and MAPEX_TORCH_THREADS=1.
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
ref=${1:-HEAD}
work=${2:-$(mktemp -d /tmp/tiny-repro.XXXXXX)}
rm -rf "$work" && mkdir -p "$work"
git -C "$here" archive "$ref" pipeline stages dvc.yaml | tar -x -C "$work"
python - "$work/params.yaml" <<PY
import sys, yaml
sys.path.insert(0, "$here/tests")
from support.tiny_params import TINY_ALL
open(sys.argv[1], "w").write(yaml.safe_dump(TINY_ALL, sort_keys=False))
PY
cd "$work"
printf '/data/\n__pycache__/\nMUJOCO_LOG.TXT\n' > .gitignore
git init -q && git config user.email t@example.com && git config user.name t
dvc init -q && git add -A && git commit -qm tiny
export MAPEX_TORCH_THREADS=1 PYTHONPATH="$work"
dvc repro > repro.log 2>&1 || { tail -40 repro.log; exit 1; }
python "$here/benchmarks/artifact_digest.py" data
