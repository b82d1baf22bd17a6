"""Seconds per MAPEX child (training only, and the 5-episode evaluation) at two settings.

    python benchmarks/bench_extract.py                  # quickstart and paper settings
    python benchmarks/bench_extract.py --paper-epochs 2 # time 2 of the paper's 20 epochs, extrapolate

Training cost does not depend on what the networks have learned, so the buffers hold random
halfcheetah-shaped rows and the critics are freshly initialised ensembles. Evaluation uses
the real env (mo-halfcheetah-v5, 750-step cap) with a fresh child policy.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from pipeline.envs import make_env
from pipeline.evaluation import eval_seeds, evaluate_policy
from pipeline.extraction import AdvantageConfig, make_child
from pipeline.nets import Actor, CriticEnsemble

OBS, ACT = 17, 6


def synthetic(rows: int, hidden: list[int], rng: np.random.Generator):
    buffers = [
        {"obs": rng.normal(size=(rows, OBS)).astype(np.float32), "action": rng.uniform(-1, 1, (rows, ACT)).astype(np.float32)}
        for _ in range(2)
    ]
    critics = [CriticEnsemble(OBS, ACT, hidden, 4).eval() for _ in range(2)]
    actors = [Actor(OBS, ACT, hidden, [-1] * ACT, [1] * ACT).eval() for _ in range(2)]
    return buffers, critics, actors


def time_child(name: str, rows: int, hidden: list[int], epochs: int, full_epochs: int, warmup: int, eval_eps: int,
               warmup_time: float | None = None) -> float:
    rng = np.random.default_rng(0)
    buffers, critics, actors = synthetic(max(rows, 1), hidden, rng)
    returns = np.array([[100.0, -3000.0], [-5.0, -10.0]])
    adv = AdvantageConfig(epochs, 1.0, 1.0, 3e-4, 256, None, "every_step", "none")
    t0 = time.perf_counter()
    child, _ = make_child(
        returns, actors, buffers, critics, hidden_sizes=hidden, child_buffer_size=rows, weight_norm="l2",
        warmup_steps=warmup, warmup_lr=3e-4, warmup_batch_size=256, adv=adv, rng=rng, torch_seed=0, device="cpu",
    )
    t_train = time.perf_counter() - t0
    steps = epochs * -(-rows // 256)
    envs = [make_env("mo-halfcheetah-v5", 750) for _ in range(eval_eps)]
    t0 = time.perf_counter()
    res = evaluate_policy(child, envs, eval_seeds(0, 0, 0, eval_eps))
    t_eval = time.perf_counter() - t0
    # The warm-up is paid once per child; only the AWR epochs scale with `full_epochs`.
    t_warm = warmup_time if warmup_time is not None else 0.0
    per_epoch = (t_train - t_warm) / epochs if epochs else None
    est = t_train if not epochs else t_warm + per_epoch * full_epochs
    print(
        f"{name}: rows {rows}, hidden {hidden}, epochs timed {epochs} of {full_epochs} ({steps} AWR steps), "
        f"warm-up {warmup} steps: train {t_train:.1f} s"
        + (f" ({per_epoch:.1f} s per AWR epoch)" if per_epoch else "")
        + f", evaluation {t_eval:.1f} s for {res.env_samples} env steps; "
        f"=> about {est + t_eval:.1f} s per child"
    )
    return t_train


def time_evaluation(eval_eps: int = 5) -> None:
    """Batched evaluation (all episodes together, one actor call per step) vs one episode at a time."""
    torch.manual_seed(0)
    actor = Actor(OBS, ACT, [256, 256], [-1] * ACT, [1] * ACT).eval()
    envs = [make_env("mo-halfcheetah-v5", 750) for _ in range(eval_eps)]
    seeds = eval_seeds(0, 0, 0, eval_eps)
    t0 = time.perf_counter()
    batched = evaluate_policy(actor, envs, seeds)
    t_batched = time.perf_counter() - t0
    t0 = time.perf_counter()
    single = [evaluate_policy(actor, envs[:1], [s]) for s in seeds]
    t_single = time.perf_counter() - t0
    assert np.allclose(batched.returns, np.concatenate([r.returns for r in single]), atol=1e-4)
    print(f"evaluation of {eval_eps} x 750 steps (256-unit actor): batched {t_batched:.2f} s, one episode at a time {t_single:.2f} s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=torch.get_num_threads())
    ap.add_argument("--paper-epochs", type=int, default=2, help="epochs actually timed at paper settings (of 20)")
    ap.add_argument("--skip-paper", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {args.threads} threads")
    time_evaluation()
    time_child("(untimed first call: allocator and kernel warm-up)", 50_000, [64, 64], 1, 1, 1000, 1)
    warm = time_child("quickstart warm-up only", 50_000, [64, 64], 0, 0, 1000, 5)
    time_child("quickstart (1 epoch, as params.yaml)", 50_000, [64, 64], 1, 1, 1000, 5, warm)
    time_child("quickstart, 3 epochs", 50_000, [64, 64], 3, 3, 1000, 5, warm)
    if not args.skip_paper:
        warm = time_child("paper warm-up only", 200_000, [256, 256], 0, 0, 1000, 5)
        time_child("paper", 200_000, [256, 256], args.paper_epochs, 20, 1000, 5, warm)


if __name__ == "__main__":
    main()
