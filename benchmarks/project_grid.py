"""The paper's grid (5 envs x 5 seeds) projected from per-core figures measured on one CPU core:
core-hours in fp32 and bf16, and the wall time of `mapex repro --ray` on C cores. Arithmetic only:
nothing is run; every input figure is a constant below with the command and date it came from
(docs/benchmarks.md), so a new measurement is one edit and a rerun.

    python benchmarks/project_grid.py                       # the tables of docs/benchmarks.md
    python benchmarks/project_grid.py --cores 8 32 64 128 --k 1 4

Model (each assumption is printed with the tables):
- A 256-unit TD3 update costs the measured HalfCheetah update scaled by its GEMM FLOPs in each
  env's observation and action sizes (benchmarks/speed_floor.py counts them); env stepping is
  about 1% of a training loop at this width and is left out of the scaling. A specialist's env
  step costs the measured `bench_specialist.py` step (update included) likewise scaled.
- A MAPEX child: its warm-up steps, its advantage-weighted steps (ceil(200,000 / 256) per epoch,
  the env's epochs: 20, Hopper and Swimmer 10) and its once-per-child work (Q(s, a) and the mean
  parent action over the hybrid rows), each from the measured HalfCheetah figure scaled by its
  GEMM FLOPs, plus the measured 1 s of its 5 evaluation episodes.
- PDERL specialists: as many TD3 updates as TD3 specialists (one per frame; its population's
  evaluation frames count in the same budget), so the same cost; at the quickstart PDERL ran
  more frames/s per process than TD3 (590-640 vs about 480), so this is an upper bound.
- MOPDERL phase 2: its two RL agents' updates, one per frame each (rl_updates_per_frame 1.0),
  over the env's phase-2 frames; evolution and episodes left out.
- MORL/D (fp32 only: morl-baselines' code): at least the quickstart's 106 frames/s (64 units)
  over 4M frames (Swimmer 2M), a lower bound (its 256-unit SAC updates cost more).
- `mapex repro --ray` on C cores: each env x seed runs its specialists (2 processes on 2 cores, one
  per objective, `train_specialist.processes: 2`) and then its extraction (1 core; sequential
  over its iterations, so more cores do not shorten it); tasks start in the order they become
  ready whenever enough cores are free (all specialists first, as submitted; a 1-core task may
  start while a 2-core one waits for cores, as Ray's scheduler allows).
  evaluate (2 processes), score and report are minutes and left out of the wall time.
"""

from __future__ import annotations

import argparse
import heapq
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from speed_floor import flops, mlp_gemms  # noqa: E402

HIDDEN = [256, 256]
BATCH = 256
ROWS = 200_000
WARMUP_STEPS = 1000
ITERATIONS = 1200

# Per-core figures (1 torch thread, 2-core AMD EPYC Zen 5 with avx512_bf16, idle), docs/benchmarks.md,
# "Precision (bfloat16) and the distance to the arithmetic", measured at 0bc96f4, recorded 104e4e7, 2026-12-02:
#   python benchmarks/bench_extract.py --only-step --precision both --threads 1 --clock cpu --step-k 1 4
#   python benchmarks/bench_specialist.py --only-update --precision both --threads 1 --clock cpu
#   python benchmarks/bench_specialist.py --no-sb3 --hidden 256 256 --stack 1 --warmup 500 --steps 1000 --precision P --threads 1
MEASURED = {
    # ms per advantage-weighted step of all K children (K: ms), HalfCheetah, 256 units, batch 256
    "awr_ms": {"fp32": {1: 5.49, 4: 19.6}, "bf16": {1: 2.74, 4: 7.42}},
    "warmup_ms": {"fp32": 2.12, "bf16": 1.41},  # one child's warm-up step
    "td3_update_ms": {"fp32": 13.9, "bf16": 6.16},  # one specialist's update (4 Q-networks)
    "specialist_steps_per_s": {"fp32": 77.7, "bf16": 155.6},  # env steps/s of one specialist with its env
    # a paper-size child's measured training seconds (K = 1), which fix its once-per-child work below
    "child_s": {"fp32": 93.0, "bf16": 46.0},
}
EVAL_S_PER_CHILD = 1.0  # "evaluation adds about 1 s" (the same section)
PDERL_FACTOR = 1.0  # PDERL specialists' cost / TD3 specialists' (an upper bound: see the docstring)
# MORL/D: 106 frames/s at the quickstart (64 units), docs/benchmarks.md "Baselines", recorded b22014b, 2026-11-23
MORLD_FRAMES_PER_S = 106.0
HALFCHEETAH = ("mo-halfcheetah-v5", 17, 6)

# env: (obs, act, AWR epochs, specialist steps per objective, MOPDERL phase-2 frames, MORL/D frames)
ENVS = {
    "mo-halfcheetah-v5": (17, 6, 20, 2_000_000, 2_000_000, 4_000_000),
    "mo-hopper-2obj-v5": (11, 3, 10, 2_000_000, 1_750_000, 4_000_000),
    "mo-walker2d-v5": (17, 6, 20, 2_000_000, 2_000_000, 4_000_000),
    "mo-ant-2obj-v5": (105, 8, 20, 2_000_000, 2_000_000, 4_000_000),
    "mo-swimmer-v5": (8, 2, 10, 1_000_000, 1_000_000, 2_000_000),
}
SEEDS = 5


def child_step_flops(obs: int, act: int, k: int = 1) -> int:
    actor, critic = [obs, *HIDDEN, act], [obs + act, *HIDDEN, 1]
    return flops(mlp_gemms(BATCH, actor, members=k, wgrad=True, xgrad=True) + 2 * mlp_gemms(k * BATCH // 2, critic, 4))


def warmup_flops(obs: int, act: int) -> int:
    return flops(mlp_gemms(BATCH, [obs, *HIDDEN, act], wgrad=True, xgrad=True))


def setup_flops(obs: int, act: int) -> int:
    """Q(s, a) of every hybrid row by its origin's 4 critic members, and 2 parents' actions."""
    return flops(mlp_gemms(ROWS, [obs + act, *HIDDEN, 1], 4) + mlp_gemms(ROWS, [obs, *HIDDEN, act], 2))


def update_flops(obs: int, act: int) -> int:
    """A TD3 update with secondary critics (2 objectives x twin heads), the actor every 2nd."""
    actor, critic = [obs, *HIDDEN, act], [obs + act, *HIDDEN, 1]
    critic_step = (
        mlp_gemms(BATCH, actor) + mlp_gemms(BATCH, critic, 4) + mlp_gemms(BATCH, critic, 4, wgrad=True, xgrad=True)
    )
    actor_step = mlp_gemms(BATCH, actor, wgrad=True, xgrad=True) + mlp_gemms(
        BATCH, critic, 1, xgrad=True, first_xgrad=True
    )
    return flops(critic_step) + flops(actor_step) // 2


def child_seconds(env: str, precision: str, k: int) -> float:
    """Seconds of one child (training and its evaluation) in `env`, trained K at a time."""
    obs, act, epochs = ENVS[env][:3]
    _, o0, a0 = HALFCHEETAH
    m = MEASURED
    steps = math.ceil(ROWS / BATCH) * epochs
    awr = m["awr_ms"][precision][k] / k * child_step_flops(obs, act, k) / child_step_flops(o0, a0, k)
    warm = m["warmup_ms"][precision] * warmup_flops(obs, act) / warmup_flops(o0, a0)
    base_steps = math.ceil(ROWS / BATCH) * 20
    once = (
        m["child_s"][precision]
        - (WARMUP_STEPS * m["warmup_ms"][precision] + base_steps * m["awr_ms"][precision][1]) / 1e3
    )
    once *= setup_flops(obs, act) / setup_flops(o0, a0)
    # the warm-up of K stacked children is taken as K warm-ups of one (not measured stacked before 2026-12-03)
    return (WARMUP_STEPS * warm + steps * awr) / 1e3 + max(once, 0.0) + EVAL_S_PER_CHILD


def specialist_hours(env: str, precision: str) -> float:
    """Core-hours of one specialist (one objective)."""
    obs, act, _, steps = ENVS[env][:4]
    per_step = (
        1 / MEASURED["specialist_steps_per_s"][precision] * update_flops(obs, act) / update_flops(*HALFCHEETAH[1:])
    )
    return steps * per_step / 3600


def mopderl_hours(env: str, precision: str) -> float:
    obs, act, _, _, frames, _ = ENVS[env]
    update = MEASURED["td3_update_ms"][precision] / 1e3 * update_flops(obs, act) / update_flops(*HALFCHEETAH[1:])
    return 2 * frames * update / 3600


def morld_hours(env: str) -> float:
    return ENVS[env][5] / MORLD_FRAMES_PER_S / 3600


def sweep_wall(cores: int, chains: list[tuple[float, float]]) -> float:
    """Hours until every (specialists h on 2 cores, extraction h on 1 core) chain is done: at
    each moment the ready tasks are started in the order they became ready, each that fits in
    the free cores (a 1-core task may start while an earlier 2-core one waits, as Ray's
    scheduler lets it)."""
    if cores < 2:
        raise ValueError("the specialists' stage needs 2 cores")
    ready = [(0.0, i, 2, spec, ext) for i, (spec, ext) in enumerate(chains)]  # (ready at, order, cores, hours, next)
    ready.sort()
    running: list[tuple[float, int, int, float]] = []  # (ends, order, cores, next extraction hours or -1)
    free, now, done = cores, 0.0, 0.0
    queue = list(ready)
    order = len(chains)
    while queue or running:
        started = True
        while started:
            started = False
            for j, (t, i, need, hours, nxt) in enumerate(queue):
                if t <= now and need <= free:
                    heapq.heappush(running, (now + hours, i, need, nxt))
                    free -= need
                    queue.pop(j)
                    started = True
                    break
        end, i, need, nxt = heapq.heappop(running)
        now, free, done = end, free + need, max(done, end)
        if nxt >= 0:
            order += 1
            queue.append((now, order, 1, nxt, -1.0))
    return done


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cores", type=int, nargs="+", default=[8, 32, 64])
    ap.add_argument("--k", type=int, nargs="+", default=[1, 4], help="children per iteration (measured: 1, 4)")
    args = ap.parse_args()
    precisions = ("fp32", "bf16")
    print("Per env and seed, core-hours (1 torch thread per process):\n")
    print("| env | TD3 specialists (2) fp32 / bf16 | 1,200 children K = " + " | K = ".join(map(str, args.k)) + " (fp32 / bf16) "
          "| PDERL specialists (2) | MOPDERL phase 2 | MORL/D (fp32) |")  # fmt: skip
    print("|---|---|" + "---|" * len(args.k) + "---|---|---|")
    totals: dict[str, float] = {}
    for env in ENVS:
        spec = {p: 2 * specialist_hours(env, p) for p in precisions}
        ext = {(p, k): ITERATIONS * child_seconds(env, p, k) / 3600 for p in precisions for k in args.k}
        mop = {p: mopderl_hours(env, p) for p in precisions}
        cells = [f"{spec['fp32']:.1f} / {spec['bf16']:.1f}"]
        cells += [f"{ext['fp32', k]:.1f} / {ext['bf16', k]:.1f}" for k in args.k]
        cells += [f"{PDERL_FACTOR * spec['fp32']:.1f} / {PDERL_FACTOR * spec['bf16']:.1f}"]
        cells += [f"{mop['fp32']:.1f} / {mop['bf16']:.1f}", f">= {morld_hours(env):.1f}"]
        print(f"| {env} | " + " | ".join(cells) + " |")
        for p in precisions:
            totals[f"spec {p}"] = totals.get(f"spec {p}", 0) + SEEDS * spec[p]
            totals[f"mop {p}"] = totals.get(f"mop {p}", 0) + SEEDS * mop[p]
            for k in args.k:
                totals[f"ext {p} {k}"] = totals.get(f"ext {p} {k}", 0) + SEEDS * ext[p, k]
        totals["morld"] = totals.get("morld", 0) + SEEDS * morld_hours(env)
    print("\nThe grid (5 envs x 5 seeds), core-hours:\n")
    print("| | fp32 | bf16 |")
    print("|---|---:|---:|")
    for k in args.k:
        row = [totals[f"spec {p}"] + totals[f"ext {p} {k}"] for p in precisions]
        print(f"| MAPEX-TD3 (TD3 specialists + 1,200 children, K = {k}) | {row[0]:,.0f} | {row[1]:,.0f} |")
    print(f"| PDERL specialists (for MAPEX-PDERL; its extraction as MAPEX-TD3's) | {PDERL_FACTOR * totals['spec fp32']:,.0f} | "
          f"{PDERL_FACTOR * totals['spec bf16']:,.0f} |")  # fmt: skip
    print(f"| MOPDERL phase 2 (from the PDERL specialists) | {totals['mop fp32']:,.0f} | {totals['mop bf16']:,.0f} |")
    print(f"| MORL/D | >= {totals['morld']:,.0f} | (fp32 only) |")
    print(
        "\nMAPEX-TD3 through `mapex repro --ray`, wall hours (25 chains: specialists on 2 cores, then extraction on 1):\n"
    )
    head = " | ".join(f"{c} cores" for c in args.cores)
    print(f"| K | precision | {head} | longest chain (bound) | core-hours / cores (bound) |")
    print("|---:|---|" + "---:|" * len(args.cores) + "---:|---|")
    for k in args.k:
        for p in precisions:
            chains = []
            for env in ENVS:
                spec, ext = specialist_hours(env, p), ITERATIONS * child_seconds(env, p, k) / 3600
                chains += [(spec, ext)] * SEEDS
            walls = [sweep_wall(c, chains) for c in args.cores]
            longest = max(s + e for s, e in chains)
            work = sum(2 * s + e for s, e in chains)
            bounds = ", ".join(f"{work / c:.0f}" for c in args.cores)
            print(f"| {k} | {p} | " + " | ".join(f"{w:.0f}" for w in walls) + f" | {longest:.0f} | {bounds} |")


if __name__ == "__main__":
    main()
