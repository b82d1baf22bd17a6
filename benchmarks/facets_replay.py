"""Did the facet rule change any draw? Replays the gaps a MAPEX run's roulette drew from, with and without
`extract.facet_bridge_ratio`, at every iteration of a run's fronts (N >= 3 objectives).

    python benchmarks/facets_replay.py FRONTS [--ratio 3.0] > replay.md

FRONTS is a method's fronts folder holding seedS/population.pt, e.g. data/fronts/mapex_td3 of a
`dvc repro` of presets/nobj/mo-hopper-v5-facets.yaml, or sweeps/facets/hopper3/data/fronts/mapex_td3
of `mapex repro presets/studies/facets.yaml`. For each seed's population and each iteration i, the
population the parents of iteration i were drawn from is every member made before it (iteration < i),
with the returns measured during extraction (what the roulette saw). Prints, per iteration, the number
of gaps without the rule (every facet of the front mesh), with it at --ratio, whether the two sets
differ, and the largest ratio on a 0.1 grid below --ratio at which the rule would first have changed
the set ("-" if none down to 1.0). Reads only; writes nothing.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from pipeline.extraction.gaps import front_gaps


def first_changing_ratio(returns: np.ndarray, below: float, every: list[tuple[int, ...]]) -> float | None:
    """The largest ratio r on the grid below - 0.1, below - 0.2, ..., 1.0 whose gaps differ from
    `every` (front_gaps(returns, None)'s gaps)."""
    every = sorted(every)
    for r in np.round(np.arange(below - 0.1, 0.99, -0.1), 1):
        if sorted(front_gaps(returns, float(r))[0]) != every:
            return float(r)
    return None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("fronts", type=Path, help="a method's fronts folder, holding seedS/population.pt")
    ap.add_argument("--ratio", type=float, default=3.0, help="the facet_bridge_ratio to compare with none")
    a = ap.parse_args()
    runs = sorted(a.fronts.glob("seed*/population.pt"))
    if not runs:
        raise SystemExit(f"{a.fronts}: no seedS/population.pt (a method's fronts folder, e.g. data/fronts/mapex_td3)")
    print(f"Gaps the roulette drew from, every facet vs facet_bridge_ratio {a.ratio} ({a.fronts})\n")
    print(
        "| seed | iteration | population | mesh points | gaps, every facet | gaps, rule | differ | rule first changes them at ratio |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for path in runs:
        pop = torch.load(path, weights_only=False)
        members = pop["members"]
        if pop["meta"]["n_objectives"] < 3:
            raise SystemExit(f"{path}: {pop['meta']['n_objectives']} objectives; the facet rule is for 3 or more")
        last = max(m["iteration"] for m in members)
        for i in range(1, last + 1):
            r = np.array([m["returns"] for m in members if m["iteration"] < i], dtype=float)
            every, _ = front_gaps(r, None)
            ruled, _ = front_gaps(r, a.ratio)
            points = len({v for g in every for v in g})
            first = first_changing_ratio(r, a.ratio, every)
            differ = "yes" if sorted(every) != sorted(ruled) else "no"
            print(
                f"| {path.parent.name[4:]} | {i} | {len(r)} | {points} | {len(every)} | {len(ruled)} | {differ} | "
                f"{'-' if first is None else first} |"
            )


if __name__ == "__main__":
    main()
