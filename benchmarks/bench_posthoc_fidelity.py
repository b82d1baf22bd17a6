"""How post-hoc critics approach the Monte-Carlo returns as they fit: fidelity per check.

Fits post-hoc critics on one specialist's buffer (as `mapex fit-critics` does, without the
stopping rule) and prints, every --check-every steps, each objective's normalised error,
Pearson correlation and mean Q vs mean return, scored with the target actor.

    python benchmarks/bench_posthoc_fidelity.py --specialist data/specialists/td3/seed0/obj0 --objective 0
    python benchmarks/bench_posthoc_fidelity.py ... --tau 0.05 --target-update-freq 1 --steps 16000
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.core.specialist import load_slot  # noqa: E402
from pipeline.critics.fidelity import score_critics  # noqa: E402
from pipeline.critics.posthoc import fit_posthoc_critics  # noqa: E402
from pipeline.params.fit_critics import FitCriticsParams  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--specialist", type=Path, required=True, help="directory with buffer.zarr and policy.pt")
    ap.add_argument("--objective", type=int, required=True)
    ap.add_argument("--steps", type=int, default=40_000)
    ap.add_argument("--check-every", type=int, default=2000)
    ap.add_argument("--tau", type=float, default=0.005)
    ap.add_argument("--target-update-freq", type=int, default=2)
    ap.add_argument("--hidden", type=int, nargs="+", default=[64, 64])
    ap.add_argument("--episodes", type=int, default=10)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    spec = load_slot(args.specialist, args.objective)
    target = spec.actor if spec.actor_target is None else spec.actor_target
    objectives = list(range(spec.buffer_attrs["n_objectives"]))
    cfg = FitCriticsParams(
        steps=args.steps,
        check_every=args.check_every,
        patience=10**9,
        tau=args.tau,
        target_update_freq=args.target_update_freq,
        hidden_sizes=args.hidden,
        device="cpu",
    )
    t0 = time.perf_counter()
    print(f"{'step':>7} {'s':>7}  " + "  ".join(f"obj{m}: err / pearson / mean Q vs G" for m in objectives))
    step = [0]

    def error(critic) -> float:
        step[0] += args.check_every
        rep = score_critics(spec.buffer, critic, objectives, target, cfg.gamma, args.episodes, 0.01)
        cols = [f"{f.rel_error:.3f} / {f.pearson:.3f} / {f.mean_q:9.1f} vs {f.mean_g:9.1f}" for f in rep.per_objective]
        print(f"{min(step[0], args.steps):7d} {time.perf_counter() - t0:7.1f}  " + "  ".join(cols), flush=True)
        return float(np.mean([f.rel_error for f in rep.per_objective]))

    fit = fit_posthoc_critics(
        spec.buffer,
        target,
        objectives,
        cfg,
        np.random.default_rng(0),
        torch.Generator().manual_seed(0),
        "cpu",
        None,
        error,
    )
    elapsed = time.perf_counter() - t0
    print(
        f"{fit.steps} steps in {elapsed:.1f} s ({fit.steps / elapsed:.0f} steps/s incl. checks, "
        f"{args.threads} thread(s)); best check at step {fit.best_step}"
    )


if __name__ == "__main__":
    main()
