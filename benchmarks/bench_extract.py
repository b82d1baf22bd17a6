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

The step part (printed first; alone with --only-step): one paper-size child step, the
project's own code (`make_children`, hence `critic_values`, `mixed_advantage`, `awr_weight`
and `regression_step`, or the stacked path for K > 1) on a hybrid buffer of --step-rows rows,
timed between consecutive steps (its on_step callback); a warm-up step (`warm_up`) likewise;
then ms per step, achieved GFLOPS, the rate of the same GEMMs alone in the same run and the
percentage (benchmarks/speed_floor.py says how FLOPs are counted), per --precision, and the
projected seconds of a paper-size child from them.

    python benchmarks/bench_extract.py --only-step --precision both     # the step lines, fp32 and bf16
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from speed_floor import (  # noqa: E402
    floor_seconds,
    flops,
    headline_rate,
    machine_lines,
    mlp_gemms,
    now,
    precisions,
    rate_line,
    set_clock,
)

from pipeline.core.envs import make_env  # noqa: E402
from pipeline.core.nets import Actor, CriticEnsemble  # noqa: E402
from pipeline.core.precision import dtype_of, frozen  # noqa: E402
from pipeline.core.seeding import derive_seeds  # noqa: E402
from pipeline.evaluation.episodes import eval_seeds, evaluate_policies  # noqa: E402
from pipeline.extraction.children import make_children  # noqa: E402
from pipeline.extraction.mapex import (  # noqa: E402
    AdvantageConfig,
    ChildConfig,
    ChildSeeds,
    critic_values,
    mean_parent_action,
    warm_up,
)

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


def config(rows: int, epochs: int, warmup: int, precision: str = "fp32") -> ChildConfig:
    """A paper child's settings (mo-halfcheetah-v5) with `rows` hybrid rows, `epochs` AWR epochs
    and `warmup` warm-up steps."""
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
    return ChildConfig(
        hidden_sizes=tuple(HIDDEN),
        child_buffer_size=rows,
        weight_norm="l2",
        warmup_steps=warmup,
        warmup_lr=3e-4,
        warmup_batch_size=256,
        adv=adv,
        precision=precision,
    )


RETURNS = np.array([[100.0, -3000.0], [-5.0, -10.0]])  # two specialists: a front of two points


def train_seconds(
    k: int, rows: int, epochs: int, warmup: int, inputs, device: torch.device, precision: str = "fp32"
) -> tuple[float, list]:
    """Wall seconds to make K children (warm-up + `epochs` AWR epochs) and the children."""
    buffers, critics, actors = inputs
    cfg = config(rows, epochs, warmup, precision)
    seeds = [ChildSeeds(*derive_seeds(0, c, n=3)) for c in range(k)]
    sync(device)
    t0 = time.perf_counter()
    children = make_children(RETURNS, actors, buffers, critics, cfg, seeds, device)
    sync(device)
    return time.perf_counter() - t0, [a for a, _ in children]


# ---------------------------------------------------------------- one step, against the arithmetic


def awr_step_gemms(k: int, batch: int = 256) -> list:
    """The GEMMs of one advantage-weighted step of K children: the actors' forward and backward
    on `batch` rows each (one batched product per layer for K > 1, a `StackedActor`), and
    Q(s, pi(s)) of every row by the critics of the specialist it came from (4 members = 2
    objectives x twin heads; about K * batch / 2 rows per specialist, all K children's rows at
    once as `critic_values` takes them)."""
    actor = [OBS, *HIDDEN, ACT]
    critic = [OBS + ACT, *HIDDEN, 1]
    return mlp_gemms(batch, actor, members=k, forward=True, wgrad=True, xgrad=True) + 2 * mlp_gemms(
        k * batch // 2, critic, members=4
    )


def warmup_step_gemms(batch: int = 256) -> list:
    """The GEMMs of one warm-up step: the actor's forward and backward."""
    return mlp_gemms(batch, [OBS, *HIDDEN, ACT], forward=True, wgrad=True, xgrad=True)


def step_ms(k: int, rows: int, steps: int, inputs, device: torch.device, precision: str) -> float:
    """Mean ms between consecutive advantage-weighted steps of K children trained together
    (K = 1: the reference `make_child` on a CPU), over `steps` steps after 20 untimed ones."""
    buffers, critics, actors = inputs
    per_epoch = math.ceil(rows / 256)
    epochs = math.ceil((steps + 21) / per_epoch)
    stamps: list[float] = []

    def on_step() -> None:
        sync(device)
        stamps.append(now())

    seeds = [ChildSeeds(*derive_seeds(0, c, n=3)) for c in range(k)]
    make_children(RETURNS, actors, buffers, critics, config(rows, epochs, 0, precision), seeds, device, on_step=on_step)
    span = stamps[20 : 21 + steps]
    return (span[-1] - span[0]) / (len(span) - 1) * 1e3


def warmup_ms(steps: int, rows: int, inputs, device: torch.device, precision: str) -> float:
    """Mean ms per warm-up step (`warm_up`) over `steps` steps (after 20 untimed ones)."""
    buffers, _, actors = inputs
    obs = torch.from_numpy(buffers[0]["obs"][:rows]).to(device)
    target = mean_parent_action(actors, obs, precision=precision)
    torch.manual_seed(1)
    actor = Actor(OBS, ACT, HIDDEN, [-1] * ACT, [1] * ACT).to(device)
    rng = np.random.default_rng(0)
    warm_up(actor, obs, target, 20, 3e-4, 256, rng, precision)
    sync(device)
    t0 = now()
    warm_up(actor, obs, target, steps, 3e-4, 256, rng, precision)
    sync(device)
    return (now() - t0) / steps * 1e3


def setup_seconds(rows: int, inputs, device: torch.device, precision: str) -> float:
    """A child's once-per-child work at `rows` hybrid rows: Q(s, a) of every row (its origin's
    critics) and the mean parent action of every row (2 parents), with the critics cast once."""
    buffers, critics, actors = inputs
    half = rows // 2
    obs = torch.from_numpy(np.concatenate([b["obs"][:half] for b in buffers])).to(device)
    act = torch.from_numpy(np.concatenate([b["action"][:half] for b in buffers])).to(device)
    origin = torch.arange(2, device=device).repeat_interleave(half)
    cast = [frozen(c, precision) for c in critics]
    sync(device)
    t0 = now()
    critic_values(cast, obs, act, origin)
    mean_parent_action(actors, obs, precision=precision)
    sync(device)
    return now() - t0


def step_report(args, inputs, device: torch.device) -> None:
    """The step lines (module docstring) for each precision asked for."""
    paper_steps = math.ceil(args.rows / 256) * PAPER_EPOCHS
    for precision in precisions(args.precision):
        dtype = dtype_of(precision)
        print(
            f"[{precision}] batched matmul 4 x 256 x 256 x 256: {headline_rate(dtype, device):.0f} GFLOPS",
            flush=True,
        )
        warm = warmup_ms(args.step_count, args.step_rows, inputs, device, precision)
        g = warmup_step_gemms()
        print(
            rate_line(
                f"warm-up step (actor {'-'.join(map(str, HIDDEN))}, batch 256)",
                precision,
                warm,
                flops(g),
                floor_seconds(g, dtype, device),
            )
        )
        awr = {}
        for k in args.step_k:
            awr[k] = step_ms(k, args.step_rows, args.step_count, inputs, device, precision)
            g = awr_step_gemms(k)
            width = "-".join(map(str, HIDDEN))
            what = f"AWR step (child + 2 x 4 critics {width}, batch 256)" + (f", K = {k} stacked" if k > 1 else "")
            print(rate_line(what, precision, awr[k], flops(g), floor_seconds(g, dtype, device)), flush=True)
        setup = setup_seconds(args.rows, inputs, device, precision)
        for k, ms in awr.items():
            child = (args.warmup_steps * warm + paper_steps * ms / k) / 1e3 + setup
            print(
                f"[{precision}] projected paper-size child{f' (K = {k})' if k > 1 else ''}: {args.warmup_steps} warm-up "
                f"steps + {paper_steps} AWR steps{f' / {k}' if k > 1 else ''} + {setup:.1f} s of Q(s, a) and mean parent "
                f"action over {args.rows} rows = {child:.1f} s of training (evaluation not included)",
                flush=True,
            )


def per_child(k: int, args, inputs, device: torch.device, precision: str = "fp32") -> float:
    """Estimated seconds per child at the paper's epochs (training; evaluation printed apart)."""
    t_warm, _ = train_seconds(k, args.rows, 0, args.warmup_steps, inputs, device, precision)
    t_train, children = train_seconds(k, args.rows, args.paper_epochs, args.warmup_steps, inputs, device, precision)
    per_epoch = (t_train - t_warm) / args.paper_epochs
    est = t_warm + per_epoch * PAPER_EPOCHS
    line = (
        f"[{precision}] K = {k:2d}: warm-up {t_warm:.1f} s, {args.paper_epochs} AWR epoch(s) {t_train - t_warm:.1f} s "
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
    ap.add_argument(
        "--precision",
        choices=["fp32", "bf16", "both"],
        default="fp32",
        help="the children's arithmetic (extract.precision); both: fp32 then bf16",
    )
    ap.add_argument("--only-step", action="store_true", help="only the step lines and their projection")
    ap.add_argument("--step-rows", type=int, default=20_000, help="hybrid rows of the step benchmark")
    ap.add_argument("--step-count", type=int, default=300, help="steps timed per step line")
    ap.add_argument("--step-k", type=int, nargs="+", default=[1], help="children trained together in the step lines")
    ap.add_argument(
        "--clock", choices=["wall", "cpu"], default="wall", help="time the step lines by wall or process CPU time"
    )
    ap.add_argument(
        "--hidden", type=int, nargs="+", default=HIDDEN, help="hidden widths of child and critics (paper: 256 256)"
    )
    args = ap.parse_args()
    set_clock(args.clock)
    HIDDEN[:] = args.hidden
    if args.paper_epochs < 1:
        ap.error("--paper-epochs must be >= 1")
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    for line in machine_lines(device):
        print(line, flush=True)
    print(
        f"hybrid {args.rows} rows, child {HIDDEN}, critics {HIDDEN} x 4 members x 2 specialists, "
        f"warm-up {args.warmup_steps} steps, batch 256",
        flush=True,
    )
    inputs = synthetic(max(args.rows, args.step_rows), device)
    step_report(args, inputs, device)
    if args.only_step:
        return
    for precision in precisions(args.precision):
        print(f"[{precision}] whole children:", flush=True)
        # untimed: allocator and kernel warm-up
        train_seconds(max(args.k), min(args.rows, 4096), 1, 5, inputs, device, precision)
        times = {k: per_child(k, args, inputs, device, precision) for k in args.k}
        base = args.k[0]
        for k in args.k[1:]:
            print(f"[{precision}] per-child training speed-up, K = {k} vs K = {base}: {times[base] / times[k]:.2f}x")


if __name__ == "__main__":
    main()
