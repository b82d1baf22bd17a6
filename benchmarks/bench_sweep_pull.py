"""How long a sweep task's pull of its upstream outputs takes, the two ways (docs/benchmarks.md,
"Sweep: pulling a report's inputs"). Run by hand on a finished sweep's cell workspace and remote:

    python benchmarks/bench_sweep_pull.py WORKSPACE REMOTE [--item report] [--way dvcyaml|paths]

It prepares a clone as a sweep task does (the commit of --repo's HEAD, the cell's params.yaml,
the upstream items' dvc.lock entries, the remote), then times `dvc pull`: `dvcyaml` pulls every
upstream output with one target (what the task does), `paths` gives each needed output as a path
target (what it did up to 1ba198e). Prints the seconds, the outputs that did not arrive, and the
size pulled.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

from pipeline.distributed.workspace import _clone_at, checkout_cell, configure_remote, stage_items


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workspace", type=Path, help="a finished cell workspace (with its dvc.lock)")
    ap.add_argument("remote", help="the sweep's DVC remote")
    ap.add_argument("--item", default="report", help="stage item whose pull is timed (default: report)")
    ap.add_argument("--way", choices=["dvcyaml", "paths"], default="dvcyaml")
    ap.add_argument("--repo", type=Path, default=Path(__file__).resolve().parents[1])
    a = ap.parse_args()
    items = {i.name: i for i in stage_items(a.workspace)}
    if a.item not in items:
        sys.exit(f"{a.workspace}: no stage item {a.item!r} (have {', '.join(sorted(items))})")
    item = items[a.item]
    lock = yaml.safe_load((a.workspace / "dvc.lock").read_text())["stages"]
    commit = subprocess.check_output(["git", "-C", str(a.repo), "rev-parse", "HEAD"], text=True).strip()
    with tempfile.TemporaryDirectory() as tmp:
        clone = Path(tmp) / "clone"
        _clone_at(str(a.repo), commit, clone)
        checkout_cell(clone, commit, (a.workspace / "params.yaml").read_text())
        configure_remote(clone, a.remote, ())
        upstream = {"schema": "2.0", "stages": {u: lock[u] for u in item.upstream}}
        (clone / "dvc.lock").write_text(yaml.safe_dump(upstream, sort_keys=False))
        dvc = shutil.which("dvc", path=str(Path(sys.executable).parent)) or "dvc"
        targets = ["--allow-missing", "dvc.yaml"] if a.way == "dvcyaml" else list(item.pull)
        t = time.monotonic()
        subprocess.run([dvc, "pull", "--quiet", *targets], cwd=clone, check=True)
        seconds = time.monotonic() - t
        missing = [p for p in item.pull if not (clone / p).exists()]
        size = sum(f.stat().st_size for f in (clone / "data").rglob("*") if f.is_file())
        print(
            f"{a.item}: {len(item.pull)} needed outputs, {len(item.upstream)} upstream items; "
            f"`dvc pull` ({a.way}) {seconds:.1f} s, {len(missing)} missing, {size / 2**20:.1f} MiB pulled"
        )


if __name__ == "__main__":
    main()
