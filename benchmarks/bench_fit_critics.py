"""Gradient steps per second of post-hoc critic fitting (pipeline.critics.posthoc) at paper sizes.

    python benchmarks/bench_fit_critics.py                     # 256-256 critics, batch 256, 2 objectives
    python benchmarks/bench_fit_critics.py --threads 1 --hidden 64 64

Speed does not depend on what is learnt, so the buffer holds random halfcheetah-shaped rows
(obs 17, act 6, 2 objectives; 100k rows by default, in RAM as a stage holds it). The first
--warmup steps are not timed. One step = one batch draw, target computation with the frozen
target policy, one Adam step of the 4-member ensemble, and a soft target update every 2nd step.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import torch

from pipeline.core.nets import Actor
from pipeline.critics.posthoc import fit_posthoc_critics
from pipeline.params.fit_critics import FitCriticsParams

OBS, ACT, N_OBJ = 17, 6, 2


def synthetic_buffer(rows: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    return {
        "obs": rng.normal(size=(rows, OBS)).astype(np.float32),
        "action": rng.uniform(-1, 1, (rows, ACT)).astype(np.float32),
        "reward": rng.normal(size=(rows, N_OBJ)).astype(np.float32),
        "next_obs": rng.normal(size=(rows, OBS)).astype(np.float32),
        "terminated": rng.random(rows) < 0.001,
        "truncated": np.zeros(rows, bool),
        "episode": np.zeros(rows, np.int64),
        "episode_step": np.zeros(rows, np.int32),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--rows", type=int, default=100_000)
    ap.add_argument("--hidden", type=int, nargs="+", default=[256, 256])
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--warmup", type=int, default=50)
    ap.add_argument("--steps", type=int, default=300, help="timed steps")
    ap.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's choice)")
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)

    data = synthetic_buffer(args.rows, np.random.default_rng(0))
    policy = Actor(OBS, ACT, args.hidden, [-1.0] * ACT, [1.0] * ACT)
    cfg = FitCriticsParams(
        steps=args.warmup + args.steps, batch_size=args.batch, hidden_sizes=args.hidden, device="cpu"
    )
    marks: dict[str, float] = {}

    def on_step(step: int, loss: torch.Tensor) -> None:
        if step == args.warmup:
            if args.device != "cpu":
                torch.cuda.synchronize()
            marks["start"] = time.perf_counter()

    gen = torch.Generator(device=args.device).manual_seed(0)
    fit_posthoc_critics(data, policy, list(range(N_OBJ)), cfg, np.random.default_rng(1), gen, args.device, on_step)
    elapsed = time.perf_counter() - marks["start"]  # fit returns float(loss): the device is synchronised
    load = os.getloadavg()[0]
    print(
        f"fit_critics: {args.steps / elapsed:.1f} gradient steps/s "
        f"(hidden {args.hidden}, batch {args.batch}, {N_OBJ} objectives = {2 * N_OBJ} critics, {args.rows} rows, "
        f"{torch.get_num_threads()} threads, device {args.device}; {args.steps} steps after {args.warmup} warm-up; "
        f"1-min load average {load:.2f} on {os.cpu_count()} CPUs)"
    )


if __name__ == "__main__":
    main()
