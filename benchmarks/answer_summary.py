"""The summary table of benchmarks/answer.sh's runs (docs/results.md section 10), in Markdown.

    python benchmarks/answer_summary.py WORKDIR > WORKDIR/summary.md

Reads WORKDIR/score/LABEL/seedS/metrics.json (benchmarks/answer_report.sh). Per method: re-evaluated
hypervolume, expected utility and distinct points (mean ± SEM over seeds), then each method paired by
seed against warm-up only and against interpolation from the same specialists, with the report's rule
(pipeline.reporting.verdicts.verdict_outcome: beyond 2 SEM of the paired differences and the same sign in
more than half of the seeds). Interpolation between shared-init specialists has specialists of its own,
so its comparison with the others is across specialist sets of the same seed, not a pairing of one set.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import yaml

from pipeline.evaluation.metrics import mean_sem
from pipeline.reporting.verdicts import verdict_outcome

LABELS = {  # the two MAPEX forms are named with their extract values by form_names()
    "paper_mapex": "MAPEX, paper form",
    "gentle_mapex": "MAPEX, gentle form",
    "warmup": "warm-up only",
    "interp": "interpolation",
    "interp_shared": "interpolation, shared-init specialists",
}


def form_names(w: Path) -> dict[str, str]:
    """The MAPEX rows' names with the values each form ran with, from WORKDIR/paper.yaml and
    WORKDIR/gentle.yaml (answer.sh writes both; a form without its file keeps the bare name)."""
    out = {}
    for label, fname in (("paper_mapex", "paper.yaml"), ("gentle_mapex", "gentle.yaml")):
        f = w / fname
        if not f.exists():
            continue
        x = (yaml.safe_load(f.read_text()) or {}).get("extract", {})
        epochs = x.get("epochs", "?")
        values = [f"{epochs} epoch{'' if epochs == 1 else 's'}", f"lr {x.get('lr', 3e-4):g}"]
        values += [f"{k} {x[k]:g}" for k in ("beta", "omega_max") if k in x]
        out[label] = f"{LABELS[label]} ({', '.join(values)})"
    return out


def load(w: Path, labels=LABELS) -> dict[str, dict[int, dict]]:
    """WORKDIR/score/LABEL/seedS/metrics.json of each of `labels`, by label and seed."""
    out: dict[str, dict[int, dict]] = {}
    for label in labels:
        for f in sorted((w / "score" / label).glob("seed*/metrics.json")):
            out.setdefault(label, {})[int(f.parent.name[4:])] = json.loads(f.read_text())
    return out


def fmt(x: float) -> str:
    return f"{x:.3g}" if abs(x) < 1e4 else f"{x:.3e}".replace("e+0", "e")


def hv_cell(scores: dict | None) -> str:
    """A per-seed table cell: hypervolume (distinct points) of a front's scores, '' where there is none."""
    return f"{fmt(scores['hypervolume'])} ({scores['distinct_count']})" if scores else ""


def ms(values: list[float]) -> str:
    m, s = mean_sem(np.array(values, dtype=float))
    return f"{fmt(m)} ± {fmt(s)}" if len(values) > 1 else fmt(m)


def paired(runs: dict, a: str, b: str) -> str:
    if a not in runs or b not in runs:
        return "–"
    seeds = sorted(set(runs[a]) & set(runs[b]))
    if len(seeds) < 2:
        return "–"
    x = np.array([runs[a][s]["front"]["hypervolume"] for s in seeds])
    y = np.array([runs[b][s]["front"]["hypervolume"] for s in seeds])
    d = x - y
    if not d.any():
        return f"identical in {len(seeds)}/{len(seeds)}"
    (dm, dsem), (bm, _) = mean_sem(d), mean_sem(y)
    word = {"beat": "**beat**", "lost": "**lost**", "tied": "tied"}[verdict_outcome(d, y, 0.05, 2.0)]
    z = f"{abs(dm) / dsem:.1f}" if dsem > 0 else "inf"
    return f"{word}: {dm / abs(bm) * 100:+.1f}%, {z} SEM, higher in {int((d > 0).sum())}/{len(seeds)}"


def main() -> None:
    w = Path(sys.argv[1])
    runs = load(w)
    if not runs:
        raise SystemExit(f"{w}/score: no LABEL/seedS/metrics.json (run benchmarks/answer_report.sh first)")
    names = {**LABELS, **form_names(w)}
    any_run = next(iter(next(iter(runs.values())).values()))
    print(
        f"env {any_run['env_id']}, reference point {any_run['reference_point']}, "
        f"{any_run['episodes']} re-evaluation episodes per member\n"
    )
    print(
        "| method | seeds | hypervolume | expected utility | distinct points | children | "
        "vs warm-up only (paired HV) | vs interpolation (paired HV) |"
    )
    print("|---|---|---|---|---|---|---|---|")
    spec: dict[int, dict] = {}  # per seed, the specialists-alone scores (the same in every run of a seed)
    for label, name in names.items():
        if label not in runs:
            continue
        r = runs[label]
        seeds = sorted(r)
        hv = [r[s]["front"]["hypervolume"] for s in seeds]
        eu = [r[s]["front"]["expected_utility"] for s in seeds]
        dc = [r[s]["front"]["distinct_count"] for s in seeds]
        if label != "interp_shared":
            spec.update({s: r[s]["specialists"] for s in seeds})
        kids = sorted({r[s]["children"] for s in seeds})
        vs_w = paired(runs, label, "warmup") if label != "warmup" else "–"
        vs_i = paired(runs, label, "interp") if label != "interp" else "–"
        print(
            f"| {name} | {','.join(map(str, seeds))} | {ms(hv)} | {ms(eu)} | {ms(dc)} | "
            f"{'/'.join(map(str, kids))} | {vs_w} | {vs_i} |"
        )

    # specialists alone: their own front's distinct points (1 where one specialist dominates the other)
    def alone(name: str, by_seed: dict[int, dict]) -> None:
        seeds = sorted(by_seed)
        cols = [ms([by_seed[s][k] for s in seeds]) for k in ("hypervolume", "expected_utility", "distinct_count")]
        print(f"| {name} | {','.join(map(str, seeds))} | {' | '.join(cols)} | 0 | | |")

    if spec:
        alone("specialists alone", spec)
    if "interp_shared" in runs:
        alone("shared-init specialists alone", {s: m["specialists"] for s, m in runs["interp_shared"].items()})
    print("\nPer seed, re-evaluated hypervolume (distinct points):\n")
    labels = [x for x in LABELS if x in runs]
    print("| seed | specialists | " + " | ".join(names[x] for x in labels) + " |")
    print("|---|---|" + "---|" * len(labels))
    for s in sorted({s for r in runs.values() for s in r}):
        print(
            f"| {s} | {hv_cell(spec.get(s))} | "
            + " | ".join(hv_cell(runs[x][s]["front"] if s in runs[x] else None) for x in labels)
            + " |"
        )
    rule = (
        "\nThe rule of 'beat'/'lost': the mean paired difference beyond 2 SEM of the paired differences and the "
        "same sign in more than half of the seeds (the report's); otherwise tied."
    )
    if "interp_shared" in runs:
        rule += " The shared-init row pairs different specialists of the same seed."
    print(rule)


if __name__ == "__main__":
    main()
