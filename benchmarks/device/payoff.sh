#!/usr/bin/env bash
# The payoff run of the paper-scale issue, for a GPU machine: TD3 specialists for every seed of
# PARAMS (one process per seed, all at once), then for every seed MAPEX in the paper's form and
# warm-up only (PARAMS's extract section) and MAPEX in the gentle form (the same with
# extract.epochs 1 and extract.lr 1e-4), all runs at once. No DVC needed: it calls the stage
# commands (python -m stages.cli) directly, in the layout dvc.yaml uses, under WORKDIR; what
# produced each run goes to WORKDIR/provenance/ (specialists/, and {paper,gentle}/fronts/).
#
#   bash benchmarks/device/payoff.sh WORKDIR [PARAMS]   (default presets/payoff/mo-halfcheetah-v5.yaml)
#
# Rerunning it continues: finished outputs are kept, a killed specialist resumes from its last
# checkpoint and a killed extraction from its last iteration (WORKDIR/resume, a folder per form).
# The machine's state lasts only while it stays warm, so start it with setsid and poll
# WORKDIR/progress.log; WORKDIR/light/ (populations, histories, learning curves, logs; a few
# MB) is what to bring back. Then benchmarks/payoff_report.sh WORKDIR re-evaluates, scores and
# reports on any machine. Run from the repository root with the dependencies importable
# (benchmarks/device/setup.sh).
set -euo pipefail
W=${1:?usage: payoff.sh WORKDIR [PARAMS]}
P=${2:-presets/payoff/mo-halfcheetah-v5.yaml}
PY=${PYTHON:-python3}
mkdir -p "$W/logs" "$W/light"
export MAPEX_RESUME_ROOT="$W/resume"
log() { echo "$(date -u +%H:%M:%S) $*" | tee -a "$W/progress.log"; }

# the two forms' params files: paper = PARAMS as given; gentle = one epoch at lr 1e-4
"$PY" - "$P" "$W" <<'PY'
import sys, yaml
from pathlib import Path
src, w = Path(sys.argv[1]), Path(sys.argv[2])
p = yaml.safe_load(src.read_text())
(w / "paper.yaml").write_text(yaml.safe_dump(p, sort_keys=False))
g = {**p, "extract": {**p["extract"], "epochs": 1, "lr": 1e-4}}
(w / "gentle.yaml").write_text(yaml.safe_dump(g, sort_keys=False))
PY
SEEDS=$("$PY" -c "import yaml,sys; print(' '.join(map(str, yaml.safe_load(open(sys.argv[1]))['seeds'])))" "$W/paper.yaml")
log "params $P, seeds $SEEDS, device: $("$PY" -c 'import torch; print(torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu")')"

run() {  # run NAME OUTPUT_FILE CMD...: skip when OUTPUT_FILE exists, else run with a log
  local name=$1 done_file=$2; shift 2
  if [ -e "$done_file" ]; then log "$name: done before"; return 0; fi
  local t0=$SECONDS
  if "$@" > "$W/logs/$name.log" 2>&1; then log "$name: done in $((SECONDS - t0)) s"
  else log "$name: FAILED after $((SECONDS - t0)) s (log: $W/logs/$name.log)"; return 1; fi
}

pids=()
for s in $SEEDS; do
  run "train_specialist_seed$s" "$W/specialists/td3/seed$s/obj1/policy.pt" \
    "$PY" -m stages.cli train-specialist --seed "$s" --out "$W/specialists/td3/seed$s" --params "$W/paper.yaml" \
    --provenance "$W/provenance/specialists/td3/seed$s.json" &
  pids+=($!)
done
for p in "${pids[@]}"; do wait "$p"; done

pids=()
for s in $SEEDS; do
  for spec in paper:mapex paper:warmup_only gentle:mapex; do
    form=${spec%%:*}; variant=${spec#*:}
    out="$W/fronts/$form/${variant}_td3/seed$s"
    run "extract_${form}_${variant}_seed$s" "$out/population.pt" \
      "$PY" -m stages.cli extract --seed "$s" --variant "$variant" --kind td3 \
      --specialists "$W/specialists/td3/seed$s" --out "$out" --params "$W/$form.yaml" \
      --provenance "$W/provenance/$form/fronts/${variant}_td3/seed$s.json" \
      --resume-dir "$W/resume/$form" &  # per form: both forms run method mapex_td3 at once
    pids+=($!)
  done
done
failed=0
for p in "${pids[@]}"; do wait "$p" || failed=1; done

# what to bring back: every small file (no buffers, checkpoints or critics)
(cd "$W" && find . -path ./light -prune -o -path ./resume -prune -o -name '*.zarr' -prune -o -type f \
   \( -name population.pt -o -name '*.csv' -o -name '*.log' -o -name '*.yaml' -o -name '*.json' \) -print \
   | tar -cf - -T - | tar -xf - -C light)
log "finished (failed: $failed); bring back $W/light ($(du -sh "$W/light" | cut -f1))"
exit $failed
