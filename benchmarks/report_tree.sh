# Sourced by benchmarks/answer_report.sh and benchmarks/facets.sh (needs W, PY and CLI set).
#
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
  # the specialists' records: the report's cost table costs them per seed and kind
  [ -d "$W/provenance/specialists" ] && mkdir -p "$t/provenance" && ln -s "$W/provenance/specialists" "$t/provenance/specialists"
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
