#!/usr/bin/env bash
# Re-evaluate, score and report the payoff run (benchmarks/device/payoff.sh) on this machine:
#
#   bash benchmarks/payoff_report.sh WORKDIR        (WORKDIR, or the light/ folder brought back)
#
# Writes WORKDIR/report/paper/ (MAPEX in the paper's form vs warm-up only) and
# WORKDIR/report/gentle/ (the gentle form vs the same warm-up only runs: the warm-up does not
# read the epochs or lr that distinguish the forms), each with report.md and figures, from the
# evaluate and score commands dvc.yaml runs, with each form's params (WORKDIR/{paper,gentle}.yaml).
set -euo pipefail
W=${1:?usage: payoff_report.sh WORKDIR}
MAPEX=${MAPEX:-mapex}
PY=${PYTHON:-python3}   # one with PyYAML (the project's .venv)
SEEDS=$("$PY" -c "import yaml,sys; print(' '.join(map(str, yaml.safe_load(open(sys.argv[1]))['seeds'])))" "$W/paper.yaml")
for form in paper gentle; do
  for s in $SEEDS; do
    for method in mapex_td3 warmup_only_td3; do
      src=$form; [ "$method" = warmup_only_td3 ] && src=paper
      pop="$W/fronts/$src/$method/seed$s/population.pt"
      ev="$W/evaluate/$form/$method/seed$s"; sc="$W/score/$form/$method/seed$s"
      prov="$W/provenance/$form"  # the records the report's provenance table shows
      [ -e "$ev/evaluated.csv" ] || $MAPEX evaluate --population "$pop" --seed "$s" --out "$ev" --params "$W/$form.yaml" \
        --provenance "$prov/evaluate/$method/seed$s.json"
      [ -e "$sc/metrics.json" ] || $MAPEX score --population "$pop" --evaluated "$ev" --out "$sc" --params "$W/$form.yaml" \
        --provenance "$prov/score/$method/seed$s.json"
      # the gentle form's warm-up only runs are the paper form's: so is their extraction record
      rec="$prov/fronts/$method/seed$s.json" src_rec="$W/provenance/$src/fronts/$method/seed$s.json"
      if [ ! -e "$rec" ] && [ -e "$src_rec" ]; then mkdir -p "$(dirname "$rec")" && cp "$src_rec" "$rec"; fi
    done
  done
  $MAPEX report --evaluated "$W/evaluate/$form" --scored "$W/score/$form" --provenance "$W/provenance/$form" \
    --out "$W/report/$form" --params "$W/$form.yaml"
  echo "$form: $W/report/$form/report.md"
done
