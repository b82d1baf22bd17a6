#!/usr/bin/env bash
# The imported-specialists path, timed step by step (docs/results.md, "Fronts from imported SB3
# specialists"): for each seed, import both specialists of presets/imported.yaml (collecting
# ROWS transitions each), fit post-hoc critics for every objective, extract MAPEX-PostHoc,
# re-evaluate and score. Run by hand, one at a time (it uses both cores' worth of one process):
#   bash benchmarks/imported_front.sh WORKDIR MODELS_DIR ROWS [SEEDS...]
# MODELS_DIR holds td3_obj0.zip and td3_obj1.zip (examples/train_sb3_specialists.py). Writes
# WORKDIR/timings.csv (seed, step, seconds) and WORKDIR/summary.csv (per seed: HV and distinct
# points of the front and of the specialists alone); prints both.
set -euo pipefail
work=$1; models=$2; rows=$3; shift 3
seeds=("${@:-0 1 2}"); [ $# -eq 0 ] && seeds=(0 1 2)
repo=$(cd "$(dirname "$0")/.." && pwd)
mkdir -p "$work"
work=$(cd "$work" && pwd)
mapex="${MAPEX:-$repo/.venv/bin/mapex}"
sed -e "s#models/td3_obj#$(cd "$models" && pwd)/td3_obj#g" -e "s/^  collect_rows: 25000 /  collect_rows: $rows /" \
  "$repo/presets/imported.yaml" > "$work/params.yaml"
grep -q "collect_rows: $rows " "$work/params.yaml" || { echo "could not set collect_rows in $work/params.yaml" >&2; exit 2; }
P=(--params "$work/params.yaml")
"$mapex" sync-params "${P[@]}"
echo "seed,step,seconds" > "$work/timings.csv"
timed() { local seed=$1 step=$2; shift 2; local t0; t0=$(date +%s.%N)
  "$@" > "$work/log_${seed}_${step}.txt" 2>&1 || { tail -5 "$work/log_${seed}_${step}.txt"; exit 1; }
  echo "$seed,$step,$(echo "$(date +%s.%N) - $t0" | bc)" >> "$work/timings.csv"; }
cd "$work"  # MuJoCo writes its log here
for s in "${seeds[@]}"; do
  d=$work/seed$s
  for k in 0 1; do
    timed "$s" "import_obj$k" "$mapex" import-specialist --seed "$s" --objective "$k" \
      --file "$(cd "$repo" && cd "$models" && pwd)/td3_obj$k.zip" --format sb3 --out "$d/specialists/obj$k" "${P[@]}"
  done
  for k in 0 1; do
    timed "$s" "fit_critics_obj$k" "$mapex" fit-critics --seed "$s" --objective "$k" --specialist "$d/specialists/obj$k" \
      --out "$d/posthoc/obj$k" "${P[@]}"
  done
  timed "$s" extract "$mapex" extract --seed "$s" --variant mapex_posthoc --kind imported --specialists "$d/specialists" \
    --posthoc "$d/posthoc" --out "$d/front" "${P[@]}"
  timed "$s" evaluate "$mapex" evaluate --seed "$s" --population "$d/front/population.pt" --out "$d/evaluate" "${P[@]}"
  timed "$s" score "$mapex" score --population "$d/front/population.pt" --evaluated "$d/evaluate" --out "$d/score" "${P[@]}"
done
"$repo/.venv/bin/python" - "$work" "${seeds[@]}" <<'PY'
import json, sys
work, seeds = sys.argv[1], sys.argv[2:]
rows = ["seed,hv_front,hv_specialists,hv_ratio,distinct_front,distinct_specialists,children,collection_frames"]
for s in seeds:
    m = json.load(open(f"{work}/seed{s}/score/metrics.json"))
    f, sp = m["front"], m["specialists"]
    rows.append(f"{s},{f['hypervolume']:.6g},{sp['hypervolume']:.6g},{m['hv_ratio_vs_specialists']:.4f},"
                f"{f['distinct_count']},{sp['distinct_count']},{m['children']},{m['env_samples_collection']}")
open(f"{work}/summary.csv", "w").write("\n".join(rows) + "\n")
print("\n".join(rows))
PY
cat "$work/timings.csv"
