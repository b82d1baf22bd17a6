#!/usr/bin/env bash
# Issue 46's figures in one run (about 3-5 minutes on an idle 2-core CPU), printed as markdown for
# docs/benchmarks.md ("Children per iteration" and "The evaluate stage in two processes"):
#   1. one paper-size child step (256 units, batch 256) for K = 1, 4, 8 and 16 children stacked, in
#      fp32 and bf16: ms per step, the percentage of the same GEMMs' rate measured in the same
#      process and of the 4x256^3 matmul's, and the projected training seconds of a paper-size
#      child (1,000 warm-up + 15,640 advantage-weighted steps over 200,000 rows) per child;
#   2. the quickstart's evaluate stage with its members in 1 and 2 processes (wall and CPU
#      seconds, and that both wrote the same bytes).
# Run it on a machine with nothing else running (the load average is printed with each part):
#   bash benchmarks/speed.sh | tee speed.txt          (or: make bench-speed)
# Uses the current environment's python (source .venv/bin/activate first). Times are process CPU
# time for the steps (--clock cpu, steadier than wall time), wall and CPU for the stage.
set -euo pipefail
cd "$(dirname "$0")/.."
python=${PYTHON:-python}
echo "## speed.sh at $(git rev-parse --short HEAD)$(git diff --quiet HEAD -- pipeline stages benchmarks || echo ' (dirty)'), $(date -u '+%Y-%m-%d %H:%M UTC')"
echo "cpu flags: $(grep -o -w -E 'avx512_bf16|amx_bf16|avx512f' /proc/cpuinfo 2>/dev/null | sort -u | tr '\n' ' ')"
echo
echo "### 1. Children per iteration (bench_extract.py)"
echo
"$python" benchmarks/bench_extract.py --only-step --precision both --threads 1 --clock cpu \
    --step-k 1 4 8 16 --step-count "${STEPS:-200}"
echo
echo "### 2. The evaluate stage in 1 and 2 processes (bench_evaluate.py)"
echo
"$python" benchmarks/bench_evaluate.py --processes 1 2 --rounds "${ROUNDS:-3}"
