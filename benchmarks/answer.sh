#!/usr/bin/env bash
# "Is a MAPEX front worth having?" (docs/results.md section 10): one design, every seed of PARAMS,
# all from the same TD3 specialists except the shared-init interpolation:
#   MAPEX in the paper's form (PARAMS's extract section), MAPEX in the gentle form (the same with
#   extract.epochs 1, extract.lr 1e-4), warm-up only, interpolation between the specialists, and
#   interpolation between specialists trained with td3.shared_init: true (SHARED_SEEDS of them).
#
#   bash benchmarks/answer.sh WORKDIR PARAMS [SLOTS]        (e.g. presets/answer/mo-halfcheetah-v5-64.yaml)
#
# SEEDS="0 1 ... 9" replaces PARAMS's seeds (e.g. to add seeds to a finished run: rerun the same
# command on the same WORKDIR with more seeds); SHARED_SEEDS (default: the seeds) picks the seeds
# of the shared-init interpolation.
#
# Runs the stage commands (python -m stages.cli) through benchmarks/jobqueue.py on SLOTS cores
# (default: nproc), longest jobs first, each once its inputs exist; every member of every front is
# re-evaluated (evaluate.episodes) and scored once; then one report per comparison under
# WORKDIR/report/{paper,gentle,shared}/ and the summary table WORKDIR/summary.md (paired
# differences against warm-up only, benchmarks/answer_summary.py). Rerunning continues: finished
# outputs are kept, killed specialists and extractions resume (WORKDIR/resume). PLAN_ONLY=1 writes
# WORKDIR/plan.tsv and stops (edit it, e.g. to reorder; the queue re-reads it while it runs).
set -euo pipefail
W=${1:?usage: answer.sh WORKDIR PARAMS [SLOTS]}
P=${2:?usage: answer.sh WORKDIR PARAMS [SLOTS]}
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
dump = lambda d: yaml.safe_dump(d, sort_keys=False, default_flow_style=None)  # lists on one line, as sync-params writes them
(w / "paper.yaml").write_text(dump(p))
g = {**p, "extract": {**p["extract"], "epochs": 1, "lr": 1e-4}}
(w / "gentle.yaml").write_text(dump(g))
s = {**p, "td3": {**p["td3"], "shared_init": True}}
(w / "shared.yaml").write_text(dump(s))
PY
# the generated run lists (td3_seeds, ...) follow the seeds: every stage checks them
for f in paper gentle shared; do $CLI sync-params --params "$W/$f.yaml" > /dev/null; done
SEEDS=$("$PY" -c "import yaml,sys; print(' '.join(map(str, yaml.safe_load(open(sys.argv[1]))['seeds'])))" "$W/paper.yaml")
SHARED_SEEDS=${SHARED_SEEDS:-$SEEDS}

# the plan: NAME, DONE, DEPS, COMMAND (tab-separated), highest priority first. A stage writes its
# provenance record after its outputs, so that record marks it done (and its outputs complete).
plan="$W/plan.tsv"
{
  line() { printf '%s\t%s\t%s\t%s\n' "$@"; }
  prov() { echo "$W/provenance/$1.json"; }
  for s in $SEEDS; do
    line "spec_td3_$s" "$(prov specialists/td3/seed$s)" - \
      "$CLI train-specialist --seed $s --out $W/specialists/td3/seed$s --params $W/paper.yaml --provenance $(prov specialists/td3/seed$s)"
  done
  # label:form:variant, the longest first (the paper form's children train 20 epochs)
  for spec in paper_mapex:paper:mapex warmup:paper:warmup_only gentle_mapex:gentle:mapex interp:paper:-; do
    IFS=: read -r label form variant <<< "$spec"
    for s in $SEEDS; do
      sp="$W/specialists/td3/seed$s" out="$W/fronts/$label/seed$s"
      if [ "$variant" = - ]; then
        cmd="$CLI interpolate --seed $s --kind td3 --specialists $sp --out $out --params $W/$form.yaml"
      else
        cmd="$CLI extract --seed $s --variant $variant --kind td3 --specialists $sp --out $out --params $W/$form.yaml --resume-dir $W/resume/$label"
      fi
      line "${label}_$s" "$(prov fronts/$label/seed$s)" "$(prov specialists/td3/seed$s)" \
        "$cmd --provenance $(prov fronts/$label/seed$s)"
    done
  done
  for label in paper_mapex warmup gentle_mapex interp; do
    for s in $SEEDS; do
      line "eval_${label}_$s" "$(prov evaluate/$label/seed$s)" "$(prov fronts/$label/seed$s)" \
        "$CLI evaluate --population $W/fronts/$label/seed$s/population.pt --seed $s --out $W/evaluate/$label/seed$s --params $W/paper.yaml --provenance $(prov evaluate/$label/seed$s)"
    done
  done
  for s in $SHARED_SEEDS; do
    d="$W/specialists/td3_shared/seed$s" out="$W/fronts/interp_shared/seed$s"
    line "spec_shared_$s" "$(prov specialists/td3_shared/seed$s)" - \
      "$CLI train-specialist --seed $s --out $d --params $W/shared.yaml --provenance $(prov specialists/td3_shared/seed$s)"
    line "interp_shared_$s" "$(prov fronts/interp_shared/seed$s)" "$(prov specialists/td3_shared/seed$s)" \
      "$CLI interpolate --seed $s --kind td3 --specialists $d --out $out --params $W/shared.yaml --provenance $(prov fronts/interp_shared/seed$s)"
    line "eval_interp_shared_$s" "$(prov evaluate/interp_shared/seed$s)" "$(prov fronts/interp_shared/seed$s)" \
      "$CLI evaluate --population $out/population.pt --seed $s --out $W/evaluate/interp_shared/seed$s --params $W/shared.yaml --provenance $(prov evaluate/interp_shared/seed$s)"
  done
} > "$plan.new"
# a plan edited by hand (e.g. reordered) is kept; pass FRESH_PLAN=1 to write it anew
[ -e "$plan" ] && [ -z "${FRESH_PLAN:-}" ] && rm "$plan.new" || mv "$plan.new" "$plan"
[ -n "${PLAN_ONLY:-}" ] && { echo "plan: $plan"; exit 0; }
"$PY" benchmarks/jobqueue.py "$plan" --slots "$SLOTS" --log "$W/logs"

bash benchmarks/answer_report.sh "$W"
