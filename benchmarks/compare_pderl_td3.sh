#!/usr/bin/env bash
# MAPEX from PDERL specialists vs from TD3 specialists at the same env frames per specialist
# (issue 9): trains both kinds for each seed, extracts with the params' `extract` section,
# re-evaluates and scores every run, and prints a table (mean hypervolume, distinct points,
# front sizes, per seed). Uses the `mapex` commands, so it measures exactly what the stages do.
#
#   benchmarks/compare_pderl_td3.sh WORKDIR [PARAMS] [SEEDS...]
#   benchmarks/compare_pderl_td3.sh /tmp/cmp params.yaml 0 1 2
#
# Budget: train_specialist.total_steps (TD3) and train_pderl.total_frames (PDERL) should be equal
# for a like-for-like comparison (the quickstart's params.yaml: 30,000 each). Runs one job at a
# time (CPU: MAPEX_TORCH_THREADS, default 1).
set -euo pipefail
work=${1:?usage: compare_pderl_td3.sh WORKDIR [PARAMS] [SEEDS...]}
params=$(realpath "${2:-params.yaml}")
shift $(( $# >= 2 ? 2 : 1 ))
seeds=("${@:-0}")
[ ${#seeds[@]} -eq 0 ] && seeds=(0)
mkdir -p "$work"
cd "$work"
for s in "${seeds[@]}"; do
  for kind in td3 pderl; do
    spec=specialists/$kind/seed$s
    if [ ! -f "$spec/obj1/critics.pt" ]; then
      start=$(date +%s)
      if [ $kind = td3 ]; then mapex train-specialist --seed "$s" --out "$spec" --params "$params"
      else mapex train-pderl --seed "$s" --out "$spec" --params "$params"; fi
      echo "$kind seed $s trained in $(( $(date +%s) - start )) s" | tee -a timings.txt
    fi
    run=$kind/seed$s
    [ -f "extract/$run/population.pt" ] || mapex extract --seed "$s" --variant mapex --kind "$kind" --specialists "$spec" \
      --out "extract/$run" --resume-dir "resume/$run" --params "$params"
    [ -f "evaluate/$run/evaluated.csv" ] || mapex evaluate --seed "$s" --population "extract/$run/population.pt" \
      --out "evaluate/$run" --params "$params"
    mapex score --population "extract/$run/population.pt" --evaluated "evaluate/$run" --out "score/$run" --params "$params"
  done
done
python - "${seeds[@]}" <<'PY'
import json, sys
import numpy as np
seeds = sys.argv[1:]
print(f"{'specialists':<12} {'HV mean':>10} {'SEM':>9} {'HV start':>10} {'x start':>8} {'distinct':>9} {'start pol.':>10}  per-seed HV")
for kind in ("td3", "pderl"):
    m = [json.load(open(f"score/{kind}/seed{s}/metrics.json")) for s in seeds]
    hv = np.array([x["front"]["hypervolume"] for x in m], float)
    hs = np.array([x["specialists"]["hypervolume"] for x in m], float)
    sem = hv.std(ddof=1) / np.sqrt(len(hv)) if len(hv) > 1 else float("nan")
    dist = np.mean([x["front"]["distinct_count"] for x in m])
    print(f"{kind:<12} {hv.mean():10.3e} {sem:9.2e} {hs.mean():10.3e} {np.mean(hv / hs):8.2f} {dist:9.1f} "
          f"{m[0]['starting_policies']:10d}  " + ", ".join(f"{h:.3e}" for h in hv))
PY
