#!/usr/bin/env bash
# Score and report benchmarks/answer.sh's runs (called at its end; rerun by hand after adding seeds):
#
#   bash benchmarks/answer_report.sh WORKDIR
#
# Scores every evaluated front once (WORKDIR/score/LABEL/seedS), then writes three reports, each
# over the seeds that have all its methods:
#   report/paper/   MAPEX in the paper's form, warm-up only, interpolation (verdicts vs warm-up only
#                   and vs interpolation)
#   report/gentle/  the same with MAPEX in the gentle form
#   report/shared/  interpolation between shared-init specialists (its own specialists: no pairs)
# and WORKDIR/summary.md, the table of docs/results.md section 10 (benchmarks/answer_summary.py).
set -euo pipefail
W=${1:?usage: answer_report.sh WORKDIR}
PY=${PYTHON:-python3}
CLI="$PY -m stages.cli"

for ev in "$W"/evaluate/*/seed*; do
  [ -e "$ev/evaluated.csv" ] || continue
  label=$(basename "$(dirname "$ev")"); seed=$(basename "$ev"); s=${seed#seed}
  params="$W/paper.yaml"; [ "$label" = gentle_mapex ] && params="$W/gentle.yaml"
  [ "$label" = interp_shared ] && params="$W/shared.yaml"
  sc="$W/score/$label/$seed"
  [ -e "$sc/metrics.json" ] || $CLI score --population "$W/fronts/$label/$seed/population.pt" --evaluated "$ev" \
    --out "$sc" --params "$params" --provenance "$W/provenance/score/$label/$seed.json"
done

# report NAME PARAMS METHOD=LABEL... (benchmarks/report_tree.sh)
source "$(dirname "$0")/report_tree.sh"
report paper "$W/paper.yaml" mapex_td3=paper_mapex warmup_only_td3=warmup interpolate_td3=interp
report gentle "$W/gentle.yaml" mapex_td3=gentle_mapex warmup_only_td3=warmup interpolate_td3=interp
report shared "$W/shared.yaml" interpolate_td3=interp_shared
"$PY" benchmarks/answer_summary.py "$W" > "$W/summary.md"
echo "summary: $W/summary.md"
