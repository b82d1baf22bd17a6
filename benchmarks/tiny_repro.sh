#!/usr/bin/env bash
# Run `dvc repro` on the every-method tiny preset (tests/support/tiny_params.py: TINY_ALL) in a fresh
# git + DVC copy of a commit, then print the digests of its data/ (benchmarks/artifact_digest.py).
# Compare two commits' digests to show a refactor changed no artifact:
#   bash benchmarks/tiny_repro.sh HEAD~5 > before.txt; bash benchmarks/tiny_repro.sh HEAD > after.txt
#   diff before.txt after.txt
# Usage: tiny_repro.sh [REF] [WORKDIR] [DIGEST OPTIONS...]   (REF default HEAD; the tiny preset is
# read from the checkout of this script, so both sides run the same params). Runs with the current
# environment's python and dvc (source .venv/bin/activate first) and MAPEX_TORCH_THREADS=1.
# A REF from before the `td3` params section gets the same values in its layout (the TD3 agent's
# keys under train_specialist); its artifacts then record their params in that layout, so compare
# such a REF with `--skip params` as a digest option (benchmarks/artifact_digest.py).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
ref=${1:-HEAD}
work=${2:-$(mktemp -d /tmp/tiny-repro.XXXXXX)}
rm -rf "$work" && mkdir -p "$work"
# the per-env facts the stages read (a DVC dep): presets/envs.yaml, or before it presets/reference_points.yaml
table=$(git -C "$here" ls-tree --name-only "$ref" presets/envs.yaml presets/reference_points.yaml)
git -C "$here" archive "$ref" pipeline stages $(git -C "$here" ls-tree --name-only "$ref" dvc.yaml) $table | tar -x -C "$work"
# the tiny preset, from this checkout's tests (its own code), then written in REF's layout by REF's code
python - > "$work/tiny.json" <<PY
import json, sys
sys.path.insert(0, "$here/tests")
from support.tiny_params import TINY_ALL
from pipeline.params.common import DERIVED_KEYS
# the keys this checkout derives, which a planning REF strips too (its own list may be older)
print(json.dumps({**TINY_ALL, "_derived_here": list(DERIVED_KEYS)}))
PY
cd "$work" && PYTHONPATH="$work" python - "$work/params.yaml" "$work/tiny.json" <<'PY'
import json, os, sys, yaml
params = json.load(open(sys.argv[2]))
derived_here = params.pop("_derived_here")
work = os.path.dirname(sys.argv[1])
if not os.path.exists(os.path.join(work, "pipeline", "params", "td3.py")):  # REF predates the td3 section
    params["train_specialist"] = {**params.pop("td3", {}), **params.get("train_specialist", {})}
if os.path.exists(os.path.join(work, "pipeline", "params", "plan.py")):
    # REF plans dvc.yaml from params.yaml (`mapex plan`): the user's keys there, then the plan
    from pipeline.params.plan import write_plan
    from pipeline.params.planned import without_derived
    from pipeline.params.tracked import tidied_text
    own = {k: v for k, v in without_derived(params).items() if k not in derived_here}
    open(sys.argv[1], "w").write(tidied_text(yaml.safe_dump(own, sort_keys=False)))
    write_plan(yaml.safe_load(open(sys.argv[1])), sys.argv[1])
elif "params.gen.yaml" in open(os.path.join(work, "dvc.yaml")).read():
    # REF keeps the derived run lists in a generated file: write both as `mapex sync-params` would
    from pipeline.params.generated import write_params_files
    write_params_files(sys.argv[1], params, sort_keys=False)
else:  # REF keeps them inline in params.yaml, and knows only the lists of its time
    for key in ("specialist_variants", "extract_variant_runs", "interpolate_variant_runs", "run_seeds",
                "run_objectives", "run_methods", "variant_labels"):
        params.pop(key, None)
    open(sys.argv[1], "w").write(yaml.safe_dump(params, sort_keys=False))
os.remove(sys.argv[2])
PY
cd "$work"
printf '/data/\n__pycache__/\nMUJOCO_LOG.TXT\n' > .gitignore
git init -q && git config user.email t@example.com && git config user.name t
dvc init -q && git add -A && git commit -qm tiny
export MAPEX_TORCH_THREADS=1 PYTHONPATH="$work"
dvc repro > repro.log 2>&1 || { tail -40 repro.log; exit 1; }
python "$here/benchmarks/artifact_digest.py" data "${@:3}"
