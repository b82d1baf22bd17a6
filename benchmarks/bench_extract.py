"""Seconds per MAPEX child at paper settings, one child at a time (K = 1) vs K children trained
together (extract.children_per_iteration), measured in one run; prints the per-child speed-up.

    python benchmarks/bench_extract.py --device cuda                    # paper: 200k rows, 20 epochs
    python benchmarks/bench_extract.py --device cpu --paper-epochs 1 --rows 20000 --warmup-steps 200

Paper settings (mo-halfcheetah-v5): 200,000-row hybrid buffer, 256-256 child, 1,000 warm-up
steps, 20 AWR epochs at batch 256, critics 256-256 with twin heads per objective, 5 evaluation
episodes of 750 steps. `--paper-epochs N` times N of the 20 epochs and extrapolates (the
warm-up is timed on its own, once per child; only the epochs scale). Training cost does not
depend on what the networks have learned, so the buffers hold random halfcheetah-shaped rows
and the critics are fresh. K = 1 runs what the stage runs: on a CPU the reference `make_child`,
on CUDA the stacked path with one child. Evaluation uses the real env, K children at once.
Timings only: nothing here is asserted (benchmarks are never timed tests).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from pipeline.core.envs import make_env
from pipeline.core.nets import Actor, CriticEnsemble
from pipeline.core.seeding import derive_seeds
from pipeline.evaluation.episodes import eval_seeds, evaluate_policies
from pipeline.extraction.children import make_children
from pipeline.extraction.mapex import AdvantageConfig, ChildConfig, ChildSeeds

OBS, ACT = 17, 6
PAPER_EPOCHS = 20  # mo-halfcheetah-v5, appendix table
HIDDEN = [256, 256]


def synthetic(rows: int, device: torch.device):
    """Two specialist buffers of `rows` rows each, their critics and two parent actors."""
    rng = np.random.default_rng(0)
    buffers = [
        {
            "obs": rng.normal(size=(rows, OBS)).astype(np.float32),
            "action": rng.uniform(-1, 1, (rows, ACT)).astype(np.float32),
        }
        for _ in range(2)
    ]
    torch.manual_seed(0)
    critics = [CriticEnsemble(OBS, ACT, HIDDEN, 4).eval().to(device) for _ in range(2)]
    actors = [Actor(OBS, ACT, HIDDEN, [-1] * ACT, [1] * ACT).eval().to(device) for _ in range(2)]
    return buffers, critics, actors


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize()


def train_seconds(k: int, rows: int, epochs: int, warmup: int, inputs, device: torch.device) -> tuple[float, list]:
    """Wall seconds to make K children (warm-up + `epochs` AWR epochs) and the children."""
    buffers, critics, actors = inputs
    returns = np.array([[100.0, -3000.0], [-5.0, -10.0]])
    adv = AdvantageConfig(
        epochs=epochs,
        beta=1.0,
        omega_max=1.0,
        lr=3e-4,
        batch_size=256,
        max_grad_norm=None,
        recompute="every_step",
        norm="none",
    )
    cfg = ChildConfig(
        hidden_sizes=tuple(HIDDEN),
        child_buffer_size=rows,
        weight_norm="l2",
        warmup_steps=warmup,
        warmup_lr=3e-4,
        warmup_batch_size=256,
        adv=adv,
    )
    seeds = [ChildSeeds(*derive_seeds(0, c, n=3)) for c in range(k)]
    sync(device)
    t0 = time.perf_counter()
    children = make_children(returns, actors, buffers, critics, cfg, seeds, device)
    sync(device)
    return time.perf_counter() - t0, [a for a, _ in children]


def per_child(k: int, args, inputs, device: torch.device) -> float:
    """Estimated seconds per child at the paper's epochs (training; evaluation printed apart)."""
    t_warm, _ = train_seconds(k, args.rows, 0, args.warmup_steps, inputs, device)
    t_train, children = train_seconds(k, args.rows, args.paper_epochs, args.warmup_steps, inputs, device)
    per_epoch = (t_train - t_warm) / args.paper_epochs
    est = t_warm + per_epoch * PAPER_EPOCHS
    line = (
        f"K = {k:2d}: warm-up {t_warm:.1f} s, {args.paper_epochs} AWR epoch(s) {t_train - t_warm:.1f} s "
        f"({per_epoch:.1f} s each) => {est:.1f} s for {k} child(ren) at {PAPER_EPOCHS} epochs, {est / k:.2f} s per child"
    )
    if not args.skip_eval:
        envs = [make_env("mo-halfcheetah-v5", 750) for _ in range(k * args.eval_episodes)]
        t0 = time.perf_counter()
        res = evaluate_policies(children, envs, [eval_seeds(0, 0, i, args.eval_episodes) for i in range(k)])
        t_eval = time.perf_counter() - t0
        line += f"; evaluation {t_eval / k:.2f} s per child ({sum(r.env_samples for r in res)} env steps in all)"
    print(line, flush=True)
    return est / k


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--threads", type=int, default=torch.get_num_threads(), help="torch CPU threads")
    ap.add_argument(
        "--paper-epochs", type=int, default=PAPER_EPOCHS, help=f"AWR epochs actually timed (of {PAPER_EPOCHS})"
    )
    ap.add_argument("--rows", type=int, default=200_000, help="hybrid buffer rows (paper: 200,000)")
    ap.add_argument("--warmup-steps", type=int, default=1000, help="warm-up steps (paper: 1,000)")
    ap.add_argument(
        "--k", type=int, nargs="+", default=[1, 16], help="children per iteration to time (first = baseline)"
    )
    ap.add_argument("--eval-episodes", type=int, default=5)
    ap.add_argument("--skip-eval", action="store_true")
    args = ap.parse_args()
    if args.paper_epochs < 1:
        ap.error("--paper-epochs must be >= 1")
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"
    print(
        f"torch {torch.__version__}, {name}, {args.threads} CPU threads; hybrid {args.rows} rows, child {HIDDEN}, "
        f"warm-up {args.warmup_steps} steps, batch 256",
        flush=True,
    )
    inputs = synthetic(args.rows, device)
    train_seconds(max(args.k), min(args.rows, 4096), 1, 5, inputs, device)  # untimed: allocator and kernel warm-up
    times = {k: per_child(k, args, inputs, device) for k in args.k}
    base = args.k[0]
    for k in args.k[1:]:
        print(f"per-child training speed-up, K = {k} vs K = {base}: {times[base] / times[k]:.2f}x")


if __name__ == "__main__":
    main()
