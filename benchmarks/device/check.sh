#!/usr/bin/env bash
# On a GPU machine, after carrying .whl (benchmarks/device/fetch_wheels.sh): install, run the
# tests that exercise the CUDA paths, then the GPU benchmarks; every result also goes to $OUT.
#
#   bash benchmarks/device/check.sh [tests|bench|all]      (default all; fits one 10-min command)
#
# tests: the specialists' and extraction's CUDA cases (skipped elsewhere): CUDA graphs vs eager,
# a run restored from a checkpoint and a SIGKILL'd stage resuming on CUDA (graphs and eager),
# K children on CUDA without per-step syncs; and the extract stage's tests, which pick CUDA there
# (extract.device: auto), including a killed extraction resuming bitwise.
# bench: specialist env steps/s for 1, 2 and 10 stacked specialists and SB3's TD3 (issue goals:
# >= 900 for one, >= 5,000 aggregate for 10), and seconds per paper-scale child for K = 1 and
# K = 16 (goal: 1,200 children <= 1 hour); PDERL frames/s against TD3's.
set -uo pipefail
cd "$(dirname "$0")/../.."
WHAT=${1:-all}
OUT=${OUT:-/tmp/mapex-device-out}
mkdir -p "$OUT"
source benchmarks/device/setup.sh "${WHEELS:-.whl}" > "$OUT/setup.txt" 2>&1  # not in a pipe: its exports must stay
cat "$OUT/setup.txt"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/gpu.txt"
if [ "$WHAT" != bench ]; then
  timeout 300 python3 -m pytest -q -p no:cacheprovider -rs tests/test_batched_specialists.py tests/test_extract_children.py tests/test_hybrid_extraction.py \
    tests/test_train_specialist.py tests/test_extract_stage.py tests/test_pderl.py::test_runs_on_cuda_and_resumes 2>&1 | tail -60 | tee "$OUT/cuda_tests.txt"
fi
if [ "$WHAT" != tests ]; then
  sb3=--no-sb3; python3 -c "import stable_baselines3" 2>/dev/null && sb3=
  timeout 200 python3 benchmarks/bench_specialist.py --device cuda --stack 2 10 $sb3 --warmup 2000 --steps 3000 \
    2>&1 | tee "$OUT/bench_specialist.txt"
  timeout 200 python3 benchmarks/bench_extract.py --device cuda --k 1 16 2>&1 | tee "$OUT/bench_extract.txt"
  # PDERL's RL agent on the graphed path vs a TD3 specialist, paper widths (not a goal of the issue)
  timeout 150 python3 benchmarks/bench_pderl.py --device cuda --frames 12000 --learning-starts 2000 2>&1 | tee "$OUT/bench_pderl.txt"
fi
