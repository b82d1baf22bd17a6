#!/usr/bin/env bash
# N >= 3 objectives: MAPEX with and without the facet rule from the same specialists (issue "The
# answer", item 7; docs/n_objectives.md, docs/results.md section 12):
#
#   bash benchmarks/facets.sh WORKDIR PARAMS [SLOTS]        (e.g. presets/nobj/mo-hopper-v5-facets.yaml)
#
# Per seed of PARAMS: one TD3 specialist per objective, one job each (so three specialists share two
# cores evenly); then from those specialists MAPEX "after" (PARAMS's extract.facet_bridge_ratio),
# MAPEX "before" (facet_bridge_ratio null: the roulette over every facet of the hull) and warm-up
# only; every member re-evaluated (evaluate.episodes) and scored; then WORKDIR/summary.md
# (benchmarks/facets_summary.py: per seed and mean ± SEM, after paired against before and both
# against warm-up only, with the report's rule), one report per MAPEX form under WORKDIR/report/,
# and WORKDIR/replay.md (benchmarks/facets_replay.py: whether the rule changed any iteration's gaps).
# Jobs run through benchmarks/jobqueue.py on SLOTS cores (default: nproc), each once its inputs'
# provenance records exist. Rerunning continues: finished outputs are kept and killed specialists and
# extractions resume (WORKDIR/resume) as long as the code they run is byte for byte the same (run it
# from a git worktree of one commit when a run spans sessions). SEEDS="..." replaces PARAMS's seeds;
# PLAN_ONLY=1 writes WORKDIR/plan.tsv and stops.
set -euo pipefail
W=${1:?usage: facets.sh WORKDIR PARAMS [SLOTS]}
P=${2:?usage: facets.sh WORKDIR PARAMS [SLOTS]}
SLOTS=${3:-$(nproc)}
PY=${PYTHON:-python3}
CLI="$PY -m stages.cli"
mkdir -p "$W"
export MAPEX_RESUME_ROOT="$W/resume"

"$PY" - "$P" "$W" <<'PY'
import os, sys, yaml
from pathlib import Path
src, w = Path(sys.argv[1]), Path(sys.argv[2])
p = yaml.safe_load(src.read_text())
if os.environ.get("SEEDS"):
    p["seeds"] = [int(x) for x in os.environ["SEEDS"].split()]
if len(p["objectives"]) < 3:
    raise SystemExit(f"{src}: objectives {p['objectives']}: the facet rule needs 3 or more objectives")
if p["extract"].get("facet_bridge_ratio") is None:
    raise SystemExit(f"{src}: extract.facet_bridge_ratio is null: 'after' needs a ratio (e.g. 3.0)")
dump = lambda d: yaml.safe_dump(d, sort_keys=False, default_flow_style=None)
(w / "after.yaml").write_text(dump(p))
(w / "before.yaml").write_text(dump({**p, "extract": {**p["extract"], "facet_bridge_ratio": None}}))
PY
for f in after before; do $CLI sync-params --params "$W/$f.yaml" > /dev/null; done
read -r -a SEEDS <<< "$("$PY" -c "import yaml,sys; print(' '.join(map(str, yaml.safe_load(open(sys.argv[1]))['seeds'])))" "$W/after.yaml")"
read -r -a OBJS <<< "$("$PY" -c "import yaml,sys; print(' '.join(map(str, yaml.safe_load(open(sys.argv[1]))['objectives'])))" "$W/after.yaml")"

plan="$W/plan.tsv"
{
  line() { printf '%s\t%s\t%s\t%s\n' "$@"; }
  prov() { echo "$W/provenance/$1.json"; }
  for s in "${SEEDS[@]}"; do
    for k in "${OBJS[@]}"; do
      line "spec_${s}_$k" "$(prov specialists/seed$s/obj$k)" - \
        "$CLI train-specialist --seed $s --objective $k --out $W/specialists/seed$s --params $W/after.yaml --provenance $(prov specialists/seed$s/obj$k)"
    done
  done
  for spec in after:after:mapex before:before:mapex warmup:after:warmup_only; do
    IFS=: read -r label form variant <<< "$spec"
    for s in "${SEEDS[@]}"; do
      deps=$(for k in "${OBJS[@]}"; do prov "specialists/seed$s/obj$k"; done | paste -sd,)
      line "${label}_$s" "$(prov fronts/$label/seed$s)" "$deps" \
        "$CLI extract --seed $s --variant $variant --kind td3 --specialists $W/specialists/seed$s --out $W/fronts/$label/seed$s --params $W/$form.yaml --resume-dir $W/resume/$label --provenance $(prov fronts/$label/seed$s)"
    done
  done
  for label in after before warmup; do
    for s in "${SEEDS[@]}"; do
      line "eval_${label}_$s" "$(prov evaluate/$label/seed$s)" "$(prov fronts/$label/seed$s)" \
        "$CLI evaluate --population $W/fronts/$label/seed$s/population.pt --seed $s --out $W/evaluate/$label/seed$s --params $W/after.yaml --provenance $(prov evaluate/$label/seed$s)"
    done
  done
} > "$plan.new"
[ -e "$plan" ] && [ -z "${FRESH_PLAN:-}" ] && rm "$plan.new" || mv "$plan.new" "$plan"
[ -n "${PLAN_ONLY:-}" ] && { echo "plan: $plan"; exit 0; }
"$PY" benchmarks/jobqueue.py "$plan" --slots "$SLOTS" --log "$W/logs"

# score every evaluated front once, then one report per MAPEX form (with warm-up only) and the summary
for ev in "$W"/evaluate/*/seed*; do
  [ -e "$ev/evaluated.csv" ] || continue
  label=$(basename "$(dirname "$ev")"); seed=$(basename "$ev")
  params="$W/after.yaml"; [ "$label" = before ] && params="$W/before.yaml"
  sc="$W/score/$label/$seed"
  [ -e "$sc/metrics.json" ] || $CLI score --population "$W/fronts/$label/$seed/population.pt" --evaluated "$ev" \
    --out "$sc" --params "$params" --provenance "$W/provenance/score/$label/$seed.json"
done
source "$(dirname "$0")/report_tree.sh"
report after "$W/after.yaml" mapex_td3=after warmup_only_td3=warmup
report before "$W/before.yaml" mapex_td3=before warmup_only_td3=warmup
"$PY" benchmarks/facets_summary.py "$W" > "$W/summary.md"
echo "summary: $W/summary.md"
# did the rule change any draw? each iteration's gaps with and without it (benchmarks/facets_replay.py)
ratio=$("$PY" -c "import yaml,sys; print(yaml.safe_load(open(sys.argv[1]))['extract'].get('facet_bridge_ratio'))" "$W/after.yaml")
if [ "$ratio" = None ]; then
  echo "replay: skipped ($P sets extract.facet_bridge_ratio null: 'after' is 'before')"
else
  "$PY" benchmarks/facets_replay.py "$W" --ratio "$ratio" > "$W/replay.md"
  echo "replay: $W/replay.md"
fi
