"""Speed of PDERL specialists against TD3 specialists: env frames per second, same budget.

Runs, on --device, one objective's specialist trained for --frames env frames twice:

  (a) TD3 with secondary critics (`pipeline.specialists.td3_training.train_specialist`; on CUDA its updates
      replay as captured CUDA graphs unless --eager);
  (b) PDERL (`pipeline.specialists.pderl.train_pderl`): the population's evaluations, evolution, the RL
      episode and one TD3 update per frame (its `TD3Learner`: the same update as (a), as CUDA
      graphs on CUDA unless --eager), then the final evaluation.

Both start updating after --learning-starts frames, so both make about frames - learning_starts
updates (PDERL a little more: its last generation runs to its end). Prints frames, updates,
wall seconds and frames/s of each, PDERL's time split (episodes, evolution, TD3 updates) and
the projected hours of a paper-scale specialist (2M frames) at each rate.

    python benchmarks/bench_pderl.py --hidden 64 64 --cap 100 --population 4 --frames 3000   # ~20 s on 2 CPU cores
    python benchmarks/bench_pderl.py --device cuda --frames 60000 --learning-starts 25000     # paper widths on a GPU
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import pipeline.specialists.pderl as pderl  # noqa: E402
from pipeline.core.envs import env_spec, make_env  # noqa: E402
from pipeline.params.td3 import TD3Params  # noqa: E402
from pipeline.params.train_pderl import TrainPderlParams  # noqa: E402
from pipeline.params.train_specialist import TrainSpecialistParams  # noqa: E402
from pipeline.specialists.td3_training import train_specialist  # noqa: E402

PAPER_FRAMES = 2_000_000


def sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


class Timer:
    """Accumulated wall time of calls to a wrapped function (synchronising a GPU around each)."""

    def __init__(self, fn, device: str):
        self.fn, self.device, self.seconds, self.calls = fn, device, 0.0, 0

    def __call__(self, *args, **kwargs):
        sync(self.device)
        t = time.perf_counter()
        out = self.fn(*args, **kwargs)
        sync(self.device)
        self.seconds += time.perf_counter() - t
        self.calls += 1
        return out


def td3_cfg(args: argparse.Namespace) -> TD3Params:
    return TD3Params(
        learning_starts=args.learning_starts,
        buffer_size=max(args.frames * 2, 1000),
        batch_size=args.batch,
        hidden_sizes=args.hidden,
        cuda_graphs=not args.eager,
    )


def bench_td3(args: argparse.Namespace) -> dict:
    cfg = td3_cfg(args)
    env = make_env(args.env, args.cap)
    spec = env_spec(env, args.env, args.cap)
    sync(args.device)
    t = time.perf_counter()
    run = TrainSpecialistParams(total_steps=args.frames, device=args.device)
    result = train_specialist(env, spec, cfg, run, args.objective, args.seed, torch.device(args.device))
    sync(args.device)
    wall = time.perf_counter() - t
    env.close()
    return {
        "name": "TD3" + (" (eager)" if args.eager or args.device == "cpu" else " (CUDA graphs)"),
        "frames": len(result.buffer["obs"]),
        "updates": args.frames - args.learning_starts,
        "wall": wall,
    }


def bench_pderl(args: argparse.Namespace) -> dict:
    cfg = TrainPderlParams(
        total_frames=args.frames,
        population_size=args.population,
        eval_episodes=1,
        mini_buffer_size=50_000,
        device=args.device,
    )
    env = make_env(args.env, args.cap)
    spec = env_spec(env, args.env, args.cap)
    episodes = Timer(pderl.PderlRun.run_episode, args.device)
    evolution = Timer(pderl.evolve, args.device)
    pderl.PderlRun.run_episode = lambda self, *a, **k: episodes(self, *a, **k)
    pderl.evolve = evolution
    sync(args.device)
    t = time.perf_counter()
    result = pderl.train_pderl(env, spec, td3_cfg(args), cfg, args.objective, args.seed, torch.device(args.device))
    sync(args.device)
    wall = time.perf_counter() - t
    env.close()
    return {
        "name": "PDERL" + (" (eager)" if args.eager or args.device == "cpu" else " (CUDA graphs)"),
        "frames": result.frames,
        "updates": result.updates,
        "wall": wall,
        "generations": len(result.history),
        "episodes_s": episodes.seconds,
        "evolution_s": evolution.seconds,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--env", default="mo-halfcheetah-v5")
    ap.add_argument("--cap", type=int, default=750, help="episode cap (paper: 750)")
    ap.add_argument("--hidden", type=int, nargs="+", default=[256, 256])
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--frames", type=int, default=20_000, help="env frames per run")
    ap.add_argument("--learning-starts", type=int, default=2_000)
    ap.add_argument("--population", type=int, default=10)
    ap.add_argument("--objective", type=int, default=0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--device", choices=["cpu", "cuda"], default="cpu")
    ap.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    ap.add_argument("--eager", action="store_true", help="TD3 without CUDA graphs")
    ap.add_argument("--skip-td3", action="store_true")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    dev = torch.cuda.get_device_name() if args.device == "cuda" else "cpu"
    print(
        f"{args.env} cap {args.cap}, hidden {args.hidden}, batch {args.batch}, {args.frames} frames "
        f"(updates from {args.learning_starts}), population {args.population}, {dev}, {args.threads} thread(s)"
    )
    rows = [] if args.skip_td3 else [bench_td3(args)]
    rows.append(bench_pderl(args))
    print(
        f"{'trainer':<22}{'frames':>9}{'updates':>9}{'wall s':>9}{'frames/s':>10}{'updates/s':>11}{'h / 2M frames':>15}"
    )
    for r in rows:
        fps = r["frames"] / r["wall"]
        print(
            f"{r['name']:<22}{r['frames']:>9}{r['updates']:>9}{r['wall']:>9.1f}{fps:>10.0f}{r['updates'] / r['wall']:>11.0f}"
            f"{PAPER_FRAMES / fps / 3600:>15.1f}"
        )
    p = rows[-1]
    rest = p["wall"] - p["episodes_s"] - p["evolution_s"]
    print(
        f"PDERL split over {p['generations']} generations: episodes {p['episodes_s']:.1f} s, evolution "
        f"{p['evolution_s']:.1f} s, TD3 updates and the rest {rest:.1f} s"
    )
    if len(rows) == 2:
        print(f"PDERL / TD3 frames/s: {(p['frames'] / p['wall']) / (rows[0]['frames'] / rows[0]['wall']):.2f}")


if __name__ == "__main__":
    main()
