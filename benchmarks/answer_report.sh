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

# report NAME PARAMS METHOD=LABEL...: a tree of links in the layout `mapex report` reads, the seeds
# that have every method scored, and the report
report() {
  local name=$1 params=$2; shift 2
  local t="$W/report-in/$name"; rm -rf "$t"
  local seeds=""
  for s in $("$PY" -c "import yaml,sys; print(' '.join(map(str, yaml.safe_load(open(sys.argv[1]))['seeds'])))" "$params"); do
    local ok=1
    for ml in "$@"; do [ -e "$W/score/${ml#*=}/seed$s/metrics.json" ] || ok=0; done
    [ $ok = 1 ] && seeds="$seeds $s"
  done
  [ -n "$seeds" ] || { echo "$name: no seed has all of $*; skipped"; return 0; }
  local methods=""
  for ml in "$@"; do
    local m=${ml%%=*} l=${ml#*=}
    methods="$methods${methods:+, }$m"
    for kind in evaluate score; do mkdir -p "$t/$kind" && ln -s "$W/$kind/$l" "$t/$kind/$m"; done
    for kind in fronts evaluate score; do
      [ -d "$W/provenance/$kind/$l" ] && mkdir -p "$t/provenance/$kind" && ln -s "$W/provenance/$kind/$l" "$t/provenance/$kind/$m"
    done
  done
  "$PY" - "$params" "$t/params.yaml" "$seeds" "$methods" <<'PY'
import sys, yaml
p = yaml.safe_load(open(sys.argv[1]))
p["seeds"] = [int(s) for s in sys.argv[3].split()]
p["methods"] = [m.strip() for m in sys.argv[4].split(",")]
open(sys.argv[2], "w").write(yaml.safe_dump(p, sort_keys=False, default_flow_style=None))
PY
  # the generated lists follow methods and seeds (the report checks them)
  $CLI sync-params --params "$t/params.yaml" > /dev/null
  $CLI report --evaluated "$t/evaluate" --scored "$t/score" --provenance "$t/provenance" --out "$W/report/$name" \
    --params "$t/params.yaml"
  echo "$name: $W/report/$name/report.md (seeds$seeds)"
}
report paper "$W/paper.yaml" mapex_td3=paper_mapex warmup_only_td3=warmup interpolate_td3=interp
report gentle "$W/gentle.yaml" mapex_td3=gentle_mapex warmup_only_td3=warmup interpolate_td3=interp
report shared "$W/shared.yaml" interpolate_td3=interp_shared
"$PY" benchmarks/answer_summary.py "$W" > "$W/summary.md"
echo "summary: $W/summary.md"
