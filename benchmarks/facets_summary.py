"""The summary of benchmarks/facets.sh's runs (the facet rule before and after, N >= 3 objectives), in Markdown.

    python benchmarks/facets_summary.py WORKDIR > WORKDIR/summary.md

Reads WORKDIR/score/{after,before,warmup}/seedS/metrics.json and the specialists' re-evaluated returns
(WORKDIR/evaluate/after/seedS/evaluated.csv). Per method: re-evaluated hypervolume, expected utility,
distinct points and sparsity (mean ± SEM over seeds), paired by seed against MAPEX without the rule
("before") and against warm-up only with the report's rule (benchmarks/answer_summary.py). Then per
seed: each specialist's returns and which specialists another one dominates (a dominated specialist
leaves a front with fewer corners than objectives, and the facet rule little to choose from).
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from answer_summary import hv_cell, load, ms, paired  # noqa: E402

LABELS = {
    "after": "MAPEX, facet rule (after)",
    "before": "MAPEX, every facet (before)",
    "warmup": "warm-up only",
}


def specialists(w: Path, seed: int) -> list[tuple[int, list[float]]]:
    """(objective, re-evaluated return vector) of each specialist of a seed, from any evaluated run."""
    for label in LABELS:
        f = w / "evaluate" / label / f"seed{seed}" / "evaluated.csv"
        if f.exists():
            rows = [r for r in csv.DictReader(f.open()) if r["origin"] == "specialist"]
            n = sum(1 for k in rows[0] if k.startswith("obj") and k[3:].isdigit())
            return [(int(r["objective"]), [float(r[f"obj{i}"]) for i in range(n)]) for r in rows]
    return []


def dominated(spec: list[tuple[int, list[float]]]) -> list[str]:
    out = []
    for a, ra in spec:
        for b, rb in spec:
            if a != b and all(x >= y for x, y in zip(rb, ra)) and any(x > y for x, y in zip(rb, ra)):
                out.append(f"{a} by {b}")
    return out


def main() -> None:
    w = Path(sys.argv[1])
    runs = load(w, LABELS)
    if not runs:
        raise SystemExit(f"{w}/score: no LABEL/seedS/metrics.json (run benchmarks/facets.sh first)")
    any_run = next(iter(next(iter(runs.values())).values()))
    print(
        f"env {any_run['env_id']}, reference point {any_run['reference_point']}, "
        f"{any_run['episodes']} re-evaluation episodes per member\n"
    )
    print(
        "| method | seeds | hypervolume | expected utility | distinct points | sparsity | children | "
        "vs every facet (paired HV) | vs warm-up only (paired HV) |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    spec_scores: dict[int, dict] = {}
    for label, name in LABELS.items():
        if label not in runs:
            continue
        r = runs[label]
        seeds = sorted(r)
        cols = [
            ms([r[s]["front"][k] for s in seeds])
            for k in ("hypervolume", "expected_utility", "distinct_count", "sparsity")
        ]
        spec_scores.update({s: r[s]["specialists"] for s in seeds})
        kids = "/".join(map(str, sorted({r[s]["children"] for s in seeds})))
        vs_b = paired(runs, label, "before") if label != "before" else "–"
        vs_w = paired(runs, label, "warmup") if label != "warmup" else "–"
        print(f"| {name} | {','.join(map(str, seeds))} | {' | '.join(cols)} | {kids} | {vs_b} | {vs_w} |")
    if spec_scores:
        seeds = sorted(spec_scores)
        cols = [
            ms([spec_scores[s][k] for s in seeds])
            for k in ("hypervolume", "expected_utility", "distinct_count", "sparsity")
        ]
        print(f"| specialists alone | {','.join(map(str, seeds))} | {' | '.join(cols)} | 0 | | |")
    print("\nPer seed, re-evaluated hypervolume (distinct points), and the specialists' returns:\n")
    labels = [x for x in LABELS if x in runs]
    print(
        "| seed | specialists | "
        + " | ".join(LABELS[x] for x in labels)
        + " | specialists' returns (objective: vector) | dominated |"
    )
    print("|---|---|" + "---|" * len(labels) + "---|---|")
    for s in sorted({s for r in runs.values() for s in r}):
        cells = [hv_cell(runs[x][s]["front"] if s in runs[x] else None) for x in labels]
        sp = hv_cell(spec_scores.get(s))
        spec = specialists(w, s)
        vec = "; ".join(f"{k}: (" + ", ".join(f"{v:.0f}" for v in r) + ")" for k, r in spec)
        print(f"| {s} | {sp} | " + " | ".join(cells) + f" | {vec} | {', '.join(dominated(spec)) or 'none'} |")
    print(
        "\nThe rule of 'beat'/'lost': the mean paired difference beyond 2 SEM of the paired differences and the "
        "same sign in more than half of the seeds (the report's); otherwise tied. 'dominated: a by b': "
        "specialist b's returns are at least specialist a's on every objective."
    )


if __name__ == "__main__":
    main()
