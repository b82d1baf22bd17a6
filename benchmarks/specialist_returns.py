"""Deterministic returns of trained specialists, seed by seed: does each one run?

For every seed directory given (a train_specialist OUT, holding obj{K}/policy.pt), evaluates
each specialist's actor for --episodes deterministic episodes of the env's cap (750 steps for
the quickstart) and prints a Markdown table: the mean undiscounted return of every objective
per specialist, then per objective the mean, median and worst over the seeds of the specialist
trained for it (the quickstart's goal: the speed specialist's worst >= 1,000 and median >= 2,000).

Usage (the quickstart's settings, seeds 0-5; train them first, e.g.
`for s in 0 1 2 3 4 5; do mapex train-specialist --seed $s --out /tmp/q/seed$s; done`):
    python benchmarks/specialist_returns.py /tmp/q/seed0 /tmp/q/seed1 ... [--episodes 5]
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.core.checkpoint import load_policy  # noqa: E402
from pipeline.core.envs import make_env  # noqa: E402
from pipeline.evaluation.episodes import eval_seeds, evaluate_policy  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("seeds", nargs="+", type=Path, help="train_specialist output directories (seed{S})")
    ap.add_argument("--episodes", type=int, default=5)
    args = ap.parse_args()
    rows, own = [], {}
    for seed_dir in args.seeds:
        for slot in sorted(seed_dir.glob("obj*/policy.pt")):
            actor, meta = load_policy(slot)
            k = meta["objective"]
            envs = [make_env(meta["env_id"], meta["max_episode_steps"]) for _ in range(args.episodes)]
            res = evaluate_policy(actor, envs, eval_seeds(meta["seed"], 7, k, args.episodes))
            rows.append((meta["seed"], k, res.mean.tolist()))
            own.setdefault(k, []).append(float(res.mean[k]))
    n_obj = len(rows[0][2])
    print("| seed | specialist | " + " | ".join(f"obj{m} return" for m in range(n_obj)) + " |")
    print("|---|---|" + "---|" * n_obj)
    for seed, k, mean in rows:
        print(f"| {seed} | obj{k} | " + " | ".join(f"{x:,.1f}" for x in mean) + " |")
    print()
    print("| specialist | on its own objective: mean | median | worst | seeds |")
    print("|---|---|---|---|---|")
    for k, vals in sorted(own.items()):
        print(
            f"| obj{k} | {statistics.mean(vals):,.1f} | {statistics.median(vals):,.1f} | {min(vals):,.1f} | {len(vals)} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
