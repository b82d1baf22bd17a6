#!/usr/bin/env bash
# The 2-core CPU figures of docs/benchmarks.md, "Specialist training at 64 units": quickstart-size specialists
# (64 units) one alone, stacked, and side by side in processes, against the one-specialist-
# per-process code of commit f0c7bf9 (before stacking), in alternating passes.
#   bash benchmarks/specialists_2core.sh [PASSES] [BASE_COMMIT]
# Run on an idle machine; figures are read by hand, never asserted.
set -euo pipefail
cd "$(dirname "$0")/.."
passes=${1:-2}
base=${2:-f0c7bf9}
py=$(pwd)/.venv/bin/python
tmp=$(mktemp -d)
old=$tmp/base
git worktree add -f -q "$old" "$base"
trap 'git worktree remove --force "$old"; rm -rf "$tmp"' EXIT
common=(--hidden 64 64 --warmup 500 --steps 2000)
for r in $(seq "$passes"); do
  for t in 1 2; do
    echo "== $base (one specialist per process), threads $t, pass $r"
    (cd "$old" && PYTHONPATH="$old" "$py" benchmarks/bench_specialist.py --only ours "${common[@]}" --threads "$t" 2>&1 | grep -E "^ours:")
  done
  echo "== now, threads 1, pass $r"
  "$py" benchmarks/bench_specialist.py --no-sb3 "${common[@]}" --stack 2 6 --processes 2 --threads 1 2>&1 | grep -E "aggregate"
  echo "== now, threads 2, pass $r"
  "$py" benchmarks/bench_specialist.py --no-sb3 "${common[@]}" --stack 2 6 --threads 2 2>&1 | grep -E "aggregate"
done
