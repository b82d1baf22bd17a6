"""Aligned interpolation on a workspace's specialists (issue 61): plain, aligned, aligned + REPAIR,
RegMean and aligned RegMean + REPAIR, each made by stage interpolate, re-evaluated by stage
evaluate and scored by stage score (the evaluator every method's front goes through), with the
core-seconds of making it. Run by hand; prints a markdown table and writes it to --out.

    python benchmarks/bench_alignment.py --workspace WS --seed 0 --out /tmp/align.md
    python benchmarks/bench_alignment.py --workspace WS --seed 0 --hybrid hybrid_td3_e2 --modes plain aligned

With --hybrid VARIANT (a named variant of mapex_td3 in WS's params, such as the study's
hybrid_td3_e2): the hybrid extraction (stage extract) with each mode's options set under that
variant's `extract` section (its interpolated starts and seed grid), instead of stage interpolate.

WS: a DVC workspace whose data/specialists/td3/seedSEED holds the specialists (with buffers) and
whose params.yaml is the run's (a cell of presets/studies/compare64.yaml, say). Nothing in WS is
written: every output goes under a temporary directory.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

from pipeline.reporting.runs import load_run

MODES = {
    "plain": {},
    "aligned": {"align": "weights"},
    "aligned + REPAIR": {"align": "weights", "repair": True},
    "RegMean (unaligned)": {"mix": "regmean"},
    "aligned RegMean + REPAIR": {"align": "weights", "mix": "regmean", "repair": True},
}


def mapex(*args: str, cwd: Path) -> None:
    # this checkout's code, not the workspace's copy (-P: the working directory is not on sys.path)
    cmd = [sys.executable, "-P", "-m", "stages.cli", *args]
    env = os.environ | {"PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    done = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, env=env)
    if done.returncode != 0:
        sys.exit(f"{' '.join(args[:1])} failed:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workspace", type=Path, required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--modes", nargs="*", default=list(MODES))
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--figure", type=Path, default=None, help="write the barrier figure of the modes here (PNG)")
    ap.add_argument("--hybrid", default=None, help="a hybrid variant of mapex_td3 to extract with each mode")
    a = ap.parse_args()
    ws = a.workspace.resolve()
    spec = ws / "data" / "specialists" / "td3" / f"seed{a.seed}"
    base = yaml.safe_load((ws / "params.yaml").read_text())
    rows, runs, labels = [], [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in a.modes:
            d = Path(tmp) / name.replace(" ", "_").replace("+", "p").replace("(", "").replace(")", "")
            d.mkdir()
            params = dict(base)
            if a.hybrid:
                variants = dict(base["variants"])
                variants[a.hybrid] = dict(variants[a.hybrid])
                variants[a.hybrid]["extract"] = {**variants[a.hybrid].get("extract", {}), **MODES[name]}
                params["variants"] = variants
            else:
                params["interpolate"] = {**(base.get("interpolate") or {}), **MODES[name]}
            (d / "params.yaml").write_text(yaml.safe_dump(params, sort_keys=False))
            p = str(d / "params.yaml")
            t0 = time.perf_counter()
            if a.hybrid:
                mapex("extract", "--seed", str(a.seed), "--variant", "mapex", "--kind", "td3", "--method", a.hybrid,
                      "--specialists", str(spec), "--out", str(d / "front"), "--params", p,
                      "--provenance", str(d / "prov.json"), "--resume-dir", str(d / "resume"), cwd=ws)  # fmt: skip
            else:
                mapex("interpolate", "--seed", str(a.seed), "--kind", "td3", "--specialists", str(spec),
                      "--out", str(d / "front"), "--params", p, "--provenance", str(d / "prov.json"), cwd=ws)  # fmt: skip
            wall = time.perf_counter() - t0
            mapex("evaluate", "--seed", str(a.seed), "--population", str(d / "front" / "population.pt"),
                  "--out", str(d / "eval"), "--params", p, cwd=ws)  # fmt: skip
            mapex("score", "--population", str(d / "front" / "population.pt"), "--evaluated", str(d / "eval"),
                  "--out", str(d / "score"), "--params", p, cwd=ws)  # fmt: skip
            metrics = json.loads((d / "score" / "metrics.json").read_text())
            cost = json.loads((d / "prov.json").read_text()).get("cost", {}).get("iterations", [])
            core = sum(r.get("train_cpu_s", 0) + r.get("eval_cpu_s", 0) for r in cost)
            mix = sum(r.get("train_cpu_s", 0) for r in cost)
            rows.append((name, metrics["front"]["hypervolume"], core, mix, wall))
            runs.append(load_run(d / "score", d / "eval", "interpolate_td3", a.seed))
            labels[name] = runs[-1]
            print(
                f"{name}: HV {metrics['front']['hypervolume']:.4g}, core-s {core:.1f} (mixing or training {mix:.2f}), wall {wall:.1f}"
            )
    part = "of which training" if a.hybrid else "of which mixing"
    table = [f"| {'hybrid ' + a.hybrid + ' with' if a.hybrid else 'interpolation'} | re-evaluated HV | vs plain | core-s making the front | {part} | wall s |",
             "|---|---|---|---|---|---|"]  # fmt: skip
    plain = rows[0][1] if rows and rows[0][0] == "plain" else None
    for name, hv, core, mix, wall in rows:
        rel = f"{(hv / plain - 1) * 100:+.1f}%" if plain else ""
        table.append(f"| {name} | {hv:.4g} | {rel} | {core:.1f} | {mix:.2f} | {wall:.1f} |")
    text = "\n".join(table)
    if a.figure and not a.hybrid:
        # one line per mode: each run gets its mode as its method name, drawn in the report's figure
        from pipeline.params.variants import parse_variants
        from pipeline.reporting.figures import barrier_figure
        from pipeline.reporting.presentation import use_variants

        keys = {n: f"interp_{i}" for i, n in enumerate(labels)}
        use_variants(parse_variants({keys[n]: {"of": "interpolate_td3", "label": n} for n in labels}))
        named = [dataclasses.replace(r, method=keys[n]) for n, r in labels.items()]
        names = base["env"].get("objective_names") or ["objective 0", "objective 1"]
        fig = barrier_figure(named, names, base["env"]["id"], a.seed, 11.0)
        fig.savefig(a.figure, dpi=110)
        print(f"figure: {a.figure}")
    print(text)
    print(f"threads: torch {os.environ.get('OMP_NUM_THREADS', 'default')}; workspace {ws}; seed {a.seed}")
    if a.out:
        a.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
