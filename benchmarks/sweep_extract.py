"""Compare extraction variants on the same specialists: final hypervolume and distinct front size.

    python benchmarks/sweep_extract.py --specialists data/specialists/td3/seed0 --params params.yaml \
        "paper:" "warmup_only:epochs=0" "range:advantage_norm=objective_range" "zscore:advantage_norm=zscore"

Each argument is NAME:KEY=VALUE,KEY=VALUE overriding the `extract` section. Every variant runs
the real `mapex extract` command into a scratch folder; the table reports, from the
extraction-time evaluations, the final hypervolume (env.reference_point), its ratio to the
specialists-only hypervolume, the front size, and the number of distinct front points
(points closer than 2% of the normalised objective range merged).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from pipeline.core.pareto import hypervolume, pareto_mask
from pipeline.core.population import load_population


def distinct(points: np.ndarray, lo: np.ndarray, hi: np.ndarray, tol: float = 0.02) -> int:
    """Greedy merge of points closer than tol (in objective space scaled to [0, 1] by lo..hi)."""
    span = np.where(hi - lo > 0, hi - lo, 1.0)
    kept: list[np.ndarray] = []
    for p in (points - lo) / span:
        if all(np.linalg.norm(p - q) >= tol for q in kept):
            kept.append(p)
    return len(kept)


def parse(spec: str) -> tuple[str, dict]:
    name, _, rest = spec.partition(":")
    updates = {}
    for item in filter(None, rest.split(",")):
        key, _, value = item.partition("=")
        updates[key] = yaml.safe_load(value)
    return name, updates


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--specialists", required=True, type=Path)
    ap.add_argument("--params", default=Path("params.yaml"), type=Path)
    ap.add_argument("--seed", default=0, type=int)
    ap.add_argument("variants", nargs="+")
    args = ap.parse_args()
    base = yaml.safe_load(args.params.read_text())
    ref = base["env"]["reference_point"]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for spec in args.variants:
            name, updates = parse(spec)
            params = {**base, "extract": {**base.get("extract", {}), **updates}}
            pfile = Path(tmp) / f"{name}.yaml"
            pfile.write_text(yaml.safe_dump(params))
            out = Path(tmp) / name
            t0 = time.perf_counter()
            r = subprocess.run(
                [
                    sys.executable,
                    "-m",
                    "stages.cli",
                    "extract",
                    "--seed",
                    str(args.seed),
                    "--specialists",
                    str(args.specialists),
                    "--out",
                    str(out),
                    "--resume-dir",
                    str(Path(tmp) / "resume" / name),
                    "--params",
                    str(pfile),
                ],
                capture_output=True,
                text=True,
            )
            wall = time.perf_counter() - t0
            if r.returncode:
                print(f"{name}: failed\n{r.stderr[-2000:]}")
                continue
            members, _ = load_population(out / "population.pt")
            ret = np.array([m.returns for m in members])
            spec_ret = ret[:2]
            front = ret[pareto_mask(ret)]
            hv, hv_s = hypervolume(ret, ref), hypervolume(spec_ret, ref)
            n_distinct = distinct(front, ret.min(0), ret.max(0))
            rows.append((name, hv, hv / hv_s if hv_s else float("nan"), len(front), n_distinct, wall))
            print(
                f"{name}: HV {hv:.4g} ({rows[-1][2]:.2f}x specialists), front {len(front)}, distinct {n_distinct}, {wall:.0f} s",
                flush=True,
            )
    print("\n| variant | HV | x specialists | front | distinct | wall s |\n|---|---|---|---|---|---|")
    for name, hv, ratio, f, d, wall in rows:
        print(f"| {name} | {hv:.4g} | {ratio:.2f} | {f} | {d} | {wall:.0f} |")


if __name__ == "__main__":
    main()
