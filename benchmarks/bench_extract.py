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
timed between consecutive steps (its on_step callback); a warm-up step of the same K children
(`warm_up` for one, `stacked_warm_up` for K > 1) likewise; then ms per step, achieved GFLOPS,
the rate of the same GEMMs alone in the same run and the percentage (benchmarks/speed_floor.py
says how FLOPs are counted), per --precision and K in --step-k, and the projected seconds of a
paper-size child from them: (warm-up steps x warm-up ms + AWR steps x AWR ms) / K plus the
child's own pass over its hybrid rows. A markdown table of every (K, precision) ends the step part.

    python benchmarks/bench_extract.py --only-step --precision both     # the step lines, fp32 and bf16
    python benchmarks/bench_extract.py --only-step --precision both --threads 1 --clock cpu --step-k 1 4 8 16
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from speed_floor import (  # noqa: E402
    clock_name,
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
from pipeline.core.nets import Actor, CriticEnsemble, StackedActor  # noqa: E402
from pipeline.core.precision import dtype_of, frozen  # noqa: E402
from pipeline.core.seeding import derive_seeds  # noqa: E402
from pipeline.evaluation.episodes import eval_seeds, evaluate_policies  # noqa: E402
from pipeline.extraction.children import make_children, stack_schedules, stacked_warm_up, warmup_schedule  # noqa: E402
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


def warmup_step_gemms(k: int = 1, batch: int = 256) -> list:
    """The GEMMs of one warm-up step of K children trained together: each actor's forward and
    backward (one batched product per layer for K > 1)."""
    return mlp_gemms(batch, [OBS, *HIDDEN, ACT], members=k, forward=True, wgrad=True, xgrad=True)


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


def warmup_ms(steps: int, rows: int, inputs, device: torch.device, precision: str, k: int = 1) -> float:
    """Mean ms per warm-up step of K children over `steps` steps (after 20 untimed ones): K = 1
    `warm_up` (what the stage runs for one child on a CPU), K > 1 `stacked_warm_up` on K copies
    of the rows (what `make_children` runs), each child on its own minibatches."""
    buffers, _, actors = inputs
    obs = torch.from_numpy(buffers[0]["obs"][:rows]).to(device)
    target = mean_parent_action(actors, obs, precision=precision)
    torch.manual_seed(1)
    children = [Actor(OBS, ACT, HIDDEN, [-1] * ACT, [1] * ACT).to(device) for _ in range(k)]
    if k == 1:
        rng = np.random.default_rng(0)
        warm_up(children[0], obs, target, 20, 3e-4, 256, rng, precision)
        sync(device)
        t0 = now()
        warm_up(children[0], obs, target, steps, 3e-4, 256, rng, precision)
        sync(device)
        return (now() - t0) / steps * 1e3
    stack = StackedActor(children)
    obs_k, target_k = obs.expand(k, *obs.shape).contiguous(), target.expand(k, *target.shape).contiguous()
    rngs = [np.random.default_rng(j) for j in range(k)]
    lap = []
    for n in (20, steps):
        rows, mask = stack_schedules([warmup_schedule(len(obs), n, 256, rng, device=device) for rng in rngs])
        sync(device)
        t0 = now()
        stacked_warm_up(stack, obs_k, target_k, rows, mask, 3e-4, precision)
        sync(device)
        lap.append(now() - t0)
    return lap[1] / steps * 1e3


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


@dataclass
class StepRow:
    """One (K, precision) line of the summary table: ms per step of all K children, and the
    rate of the step against its own GEMMs and against the headline matmul."""

    k: int
    precision: str
    awr_ms: float
    awr_pct: float  # % of the rate of its own GEMMs alone
    awr_headline_pct: float  # % of the headline matmul's rate (4 x 256^3)
    warm_ms: float
    warm_pct: float
    child_s: float  # projected training seconds of one paper-size child


def step_report(args, inputs, device: torch.device) -> list[StepRow]:
    """The step lines (module docstring) for each precision asked for; returns the table rows."""
    paper_steps = math.ceil(args.rows / 256) * PAPER_EPOCHS
    width = "-".join(map(str, HIDDEN))
    table = []
    for precision in precisions(args.precision):
        dtype = dtype_of(precision)
        headline = headline_rate(dtype, device)
        print(f"[{precision}] batched matmul 4 x 256 x 256 x 256: {headline:.0f} GFLOPS", flush=True)
        setup = setup_seconds(args.rows, inputs, device, precision)
        for k in args.step_k:
            stacked = f", K = {k} stacked" if k > 1 else ""
            warm = warmup_ms(args.step_count, args.step_rows, inputs, device, precision, k)
            gw = warmup_step_gemms(k)
            print(
                rate_line(
                    f"warm-up step (actor {width}, batch 256){stacked}",
                    precision,
                    warm,
                    flops(gw),
                    fw := floor_seconds(gw, dtype, device),
                ),
                flush=True,
            )
            awr = step_ms(k, args.step_rows, args.step_count, inputs, device, precision)
            g = awr_step_gemms(k)
            fa = floor_seconds(g, dtype, device)
            print(
                rate_line(f"AWR step (child + 2 x 4 critics {width}, batch 256){stacked}", precision, awr, flops(g), fa)
            )
            child = (args.warmup_steps * warm + paper_steps * awr) / k / 1e3 + setup
            print(
                f"[{precision}] projected paper-size child (K = {k}): ({args.warmup_steps} warm-up steps + {paper_steps} "
                f"AWR steps) / {k} + {setup:.1f} s of Q(s, a) and mean parent action over {args.rows} rows = "
                f"{child:.1f} s of training (evaluation not included)",
                flush=True,
            )
            rate = flops(g) / (awr / 1e3) / 1e9
            table.append(
                StepRow(
                    k, precision, awr, 100 * fa * 1e3 / awr, 100 * rate / headline, warm, 100 * fw * 1e3 / warm, child
                )
            )
    return table


def markdown_table(rows: list[StepRow]) -> str:
    """The summary of the step lines, as docs/benchmarks.md prints it."""
    out = [
        "| K | precision | AWR step, all K (ms) | % of its GEMMs' rate | % of the 4x256^3 matmul rate "
        "| warm-up step, all K (ms) | % of its GEMMs' rate | paper-size child (s) |",
        "|---:|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        out.append(
            f"| {r.k} | {r.precision} | {r.awr_ms:.2f} | {r.awr_pct:.0f}% | {r.awr_headline_pct:.0f}% "
            f"| {r.warm_ms:.2f} | {r.warm_pct:.0f}% | {r.child_s:.1f} |"
        )
    return "\n".join(out)


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
    table = step_report(args, inputs, device)
    print(
        f"\nSummary ({clock_name()} clock; per-child seconds: {args.warmup_steps} warm-up + "
        f"{math.ceil(args.rows / 256) * PAPER_EPOCHS}"
        f" AWR steps over {args.rows} rows, projected from {args.step_count} timed steps on {args.step_rows} rows):\n",
        flush=True,
    )
    print(markdown_table(table), flush=True)
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
