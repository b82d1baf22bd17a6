"""Speed of specialist training: one specialist, K stacked in one process, and stable-baselines3.

Measures env steps per second after the warm-up (each such step does one gradient update per
specialist), on --device cpu or cuda, in one run:

  (a) our TD3 specialist with secondary critics alone (2 objectives x 2 heads = 4 Q-networks);
  (b) K of them stacked in one process (`train_specialists`): aggregate and per-specialist;
      with --processes P also K of them split over P side-by-side processes (K/P stacked in
      each, as `train_specialist.processes` runs them), aggregate;
  (c) stable-baselines3's TD3 (2 Q-networks) on the same env reduced to one objective, with the
      same widths, batch, warm-up, thread count and device;

and prints the ratios (b)/(a) aggregate and (a)/(c), then the projected hours of the
specialists of one paper-scale env x seed (2 objectives x 2M steps) at rates (a) and (b).

    pip install -e ".[bench]"          # stable-baselines3
    python benchmarks/bench_specialist.py --device cpu --hidden 64 64 --stack 2       # the quickstart's networks
    python benchmarks/bench_specialist.py --device cuda --stack 2 10 --steps 5000     # paper widths on a GPU

First, the update alone (printed first; alone with --only-update): one specialist's TD3 update
(the stage's `Updater`: minibatch draw, critic step, and the actor step with the Polyak updates
every td3.policy_freq-th update) on a filled buffer of random rows, per --precision: ms per
update, achieved GFLOPS, the rate of the same GEMMs alone in the same run and the percentage
(benchmarks/speed_floor.py says how FLOPs are counted), and the env steps/s that would leave
per core if the env cost nothing.

    python benchmarks/bench_specialist.py --only-update --precision both       # paper widths, fp32 and bf16

Warm-up steps (uniform random actions, no updates) are not timed; on CUDA the graph capture
happens at the first update, inside the timed part (it costs well under a second). Each side
reports steps per wall-second and per CPU-second of its process; on a shared machine the
second is the steadier figure on a CPU.
"""

from __future__ import annotations

import argparse
import os
import platform
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

from pipeline.core.buffer import StackedReplay  # noqa: E402
from pipeline.core.envs import env_spec, make_env  # noqa: E402
from pipeline.core.precision import dtype_of  # noqa: E402
from pipeline.params.td3 import TD3Params  # noqa: E402
from pipeline.params.train_specialist import TrainSpecialistParams  # noqa: E402
from pipeline.specialists.td3 import Updater, init_stacked, run_seeds  # noqa: E402
from pipeline.specialists.td3_training import train_specialists  # noqa: E402


def load() -> str:
    return "load average {:.2f} {:.2f} {:.2f}".format(*os.getloadavg())


def clocks() -> tuple[float, float]:
    """(wall, CPU time of this process): on a shared machine the CPU time is the steadier one."""
    return time.perf_counter(), time.process_time()


def update_gemms(obs: int, act: int, hidden: list[int], n_obj: int, batch: int) -> tuple[list, list]:
    """The GEMMs of one specialist's critic step and of its actor step (benchmarks/speed_floor.py).

    Critic step: the target actor at s', the target critics (2 heads per objective) at
    (s', a'), the online critics forward and backward (weights and inputs but the first
    layer's). Actor step: the actor forward and backward, the primary critic member forward
    and backward to its input (dQ/da; its weights get no gradient).
    """
    actor, critic, e = [obs, *hidden, act], [obs + act, *hidden, 1], 2 * n_obj
    critic_step = mlp_gemms(batch, actor) + mlp_gemms(batch, critic, e)
    critic_step += mlp_gemms(batch, critic, e, wgrad=True, xgrad=True)
    actor_step = mlp_gemms(batch, actor, wgrad=True, xgrad=True)
    actor_step += mlp_gemms(batch, critic, 1, xgrad=True, first_xgrad=True)
    return critic_step, actor_step


def update_report(args: argparse.Namespace) -> None:
    """The update lines (module docstring) for each precision asked for."""
    env = make_env(args.env, args.cap)
    spec = env_spec(env, args.env, args.cap)
    env.close()
    device = torch.device(args.device)
    rows = 20_000
    rng = np.random.default_rng(0)
    data = {
        "obs": rng.normal(size=(rows, spec.obs_dim)).astype(np.float32),
        "action": rng.uniform(-1, 1, (rows, spec.act_dim)).astype(np.float32),
        "reward": rng.normal(size=(rows, spec.n_objectives)).astype(np.float32),
        "next_obs": rng.normal(size=(rows, spec.obs_dim)).astype(np.float32),
        "terminated": np.zeros(rows, bool),
        "truncated": np.zeros(rows, bool),
        "episode": np.zeros(rows, np.int64),
        "episode_step": np.zeros(rows, np.int32),
    }
    td3 = TD3Params(batch_size=args.batch, hidden_sizes=args.hidden, secondary_critics=not args.no_secondary)
    n_obj = spec.n_objectives if td3.secondary_critics else 1
    critic_g, actor_g = update_gemms(spec.obs_dim, spec.act_dim, list(args.hidden), n_obj, args.batch)
    per_update = flops(critic_g) + flops(actor_g) / td3.policy_freq
    for precision in precisions(args.precision):
        dtype = dtype_of(precision)
        print(
            f"[{precision}] batched matmul 4 x 256 x 256 x 256: {headline_rate(dtype, device):.0f} GFLOPS", flush=True
        )
        jobs = [(args.seed, 0)]
        seeds = [run_seeds(*j) for j in jobs]
        state = init_stacked(spec, td3, jobs, device)
        buffer = StackedReplay(1, rows, spec.obs_dim, spec.act_dim, spec.n_objectives, device)
        buffer.fill(data)
        update = Updater(state, buffer, td3, seeds, [np.random.default_rng(0)], device, precision)
        n = args.update_count - args.update_count % td3.policy_freq
        for t in range(1, 21):
            update(update_actor=t % td3.policy_freq == 0)
        if device.type == "cuda":
            torch.cuda.synchronize()
        t0 = now()
        for t in range(1, n + 1):
            update(update_actor=t % td3.policy_freq == 0)
        if device.type == "cuda":
            torch.cuda.synchronize()
        ms = (now() - t0) / n * 1e3
        floor = floor_seconds(critic_g, dtype, device) + floor_seconds(actor_g, dtype, device) / td3.policy_freq
        what = f"TD3 update ({2 * n_obj} Q-networks {args.hidden}, actor, batch {args.batch}, actor every {td3.policy_freq})"
        print(rate_line(what, precision, ms, int(per_update), floor), flush=True)
        print(f"[{precision}] at most {1e3 / ms:.0f} env steps/s per core with a free env ({load()})", flush=True)


def bench_ours(args: argparse.Namespace, stack: int, first: int = 0) -> tuple[tuple[float, float], int]:
    """`stack` specialists (objectives alternating, seeds counting up, from the first-th) trained
    together; returns ((wall s, CPU s) of the timed steps, Q-networks trained per specialist)."""
    td3 = TD3Params(
        learning_starts=args.warmup,
        buffer_size=args.warmup + args.steps,
        batch_size=args.batch,
        hidden_sizes=args.hidden,
        secondary_critics=not args.no_secondary,
    )
    cfg = TrainSpecialistParams(
        total_steps=args.warmup + args.steps, device=args.device, precision=precisions(args.precision)[0]
    )
    envs = [make_env(args.env, args.cap) for _ in range(stack)]
    spec = env_spec(envs[0], args.env, args.cap)
    jobs = [(args.seed + s // spec.n_objectives, s % spec.n_objectives) for s in range(first, first + stack)]
    start: list[tuple[float, float]] = []

    def on_step(t: int, _records) -> None:
        if t == args.warmup:  # the last warm-up step is done; updates start with the next one
            start.append(clocks())

    results = train_specialists(envs, spec, td3, cfg, jobs, torch.device(args.device), on_step=on_step)
    if args.device == "cuda":
        torch.cuda.synchronize()
    end = clocks()
    for env in envs:
        env.close()
    return (end[0] - start[0][0], end[1] - start[0][1]), results[0].critic.n_members


def bench_part(args: argparse.Namespace, stack: int, first: int, *, send) -> None:
    """One process of a side-by-side run (pipeline.core.workers): its share, stacked."""
    torch.set_num_threads(args.threads)
    send(bench_ours(args, stack, first)[0])


def bench_side_by_side(args: argparse.Namespace, stack: int, processes: int) -> tuple[float, float]:
    """`stack` specialists split over `processes` processes at once (contiguous shares, sizes
    differing by one at most); returns (aggregate steps/s, per CPU-second): each process's
    timed steps over its own wall (CPU) time, summed."""
    from pipeline.core.workers import run_side_by_side

    sizes = [stack // processes + (i < stack % processes) for i in range(processes)]
    parts = [(args, k, sum(sizes[:i])) for i, k in enumerate(sizes)]
    clocks_of: dict[int, tuple[float, float]] = {}
    run_side_by_side(bench_part, parts, lambda i, message: clocks_of.__setitem__(i, message[0]))
    wall = sum(k * args.steps / clocks_of[i][0] for i, k in enumerate(sizes))
    cpu = sum(k * args.steps / clocks_of[i][1] for i, k in enumerate(sizes))
    return wall, cpu


def bench_sb3(args: argparse.Namespace) -> tuple[float, float]:
    """stable-baselines3 TD3 on objective `args.objective` of the same env; returns (wall s, CPU s)."""
    from mo_gymnasium.wrappers import LinearReward
    from stable_baselines3 import TD3
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.noise import NormalActionNoise

    base = make_env(args.env, args.cap)
    n_obj = base.unwrapped.reward_space.shape[0]
    env = LinearReward(base, weight=np.eye(n_obj, dtype=np.float32)[args.objective])
    half_range = (env.action_space.high - env.action_space.low) / 2
    act_dim = env.action_space.shape[0]

    start: list[tuple[float, float]] = []

    class StartTimer(BaseCallback):
        def _on_step(self) -> bool:  # called after each env step, before that step's update
            if self.num_timesteps == args.warmup:
                start.append(clocks())
            return True

    model = TD3(
        "MlpPolicy",
        env,
        learning_rate=3e-4,
        buffer_size=args.warmup + args.steps,
        learning_starts=args.warmup,
        batch_size=args.batch,
        tau=0.005,
        gamma=0.99,
        train_freq=1,
        gradient_steps=1,
        action_noise=NormalActionNoise(np.zeros(act_dim), 0.1 * half_range),
        policy_delay=2,
        target_policy_noise=0.2,
        target_noise_clip=0.5,
        policy_kwargs={"net_arch": {"pi": list(args.hidden), "qf": list(args.hidden)}},
        seed=args.seed,
        device=args.device,
        verbose=0,
    )
    model.learn(total_timesteps=args.warmup + args.steps, callback=StartTimer())
    end = clocks()
    env.close()
    return end[0] - start[0][0], end[1] - start[0][1]


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--env", default="mo-halfcheetah-v5", help="MO-Gymnasium env id")
    parser.add_argument("--cap", type=int, default=750, help="episode cap (max_episode_steps)")
    parser.add_argument("--objective", type=int, default=0, help="SB3 trains this objective alone")
    parser.add_argument("--device", choices=["cpu", "cuda"], default="cpu", help="device of every side")
    parser.add_argument(
        "--stack", type=int, nargs="+", default=[2], help="K: specialists stacked in one process (one run per K)"
    )
    parser.add_argument("--warmup", type=int, default=2000, help="random-action steps before updates (not timed)")
    parser.add_argument("--steps", type=int, default=3000, help="timed steps after the warm-up, one update each")
    parser.add_argument("--batch", type=int, default=256, help="minibatch size")
    parser.add_argument("--hidden", type=int, nargs="+", default=[256, 256], help="hidden widths of actor and critics")
    parser.add_argument(
        "--threads", type=int, default=1, help="torch intra-op threads, the same for every side (and process)"
    )
    parser.add_argument(
        "--processes",
        type=int,
        default=1,
        help="P > 1: also run each K split over P side-by-side processes (train_specialist.processes)",
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-secondary", action="store_true", help="ours without secondary critics (2 Q-networks)")
    parser.add_argument("--no-sb3", action="store_true", help="skip stable-baselines3")
    parser.add_argument(
        "--paper-steps", type=float, default=2e6, help="specialist steps per objective in the projection"
    )
    parser.add_argument(
        "--precision",
        choices=["fp32", "bf16", "both"],
        default="fp32",
        help="the updates' arithmetic (train_specialist.precision); both: the update lines in each, "
        "the env runs in the first",
    )
    parser.add_argument("--only-update", action="store_true", help="only the update lines")
    parser.add_argument("--update-count", type=int, default=400, help="updates timed per update line")
    parser.add_argument(
        "--clock", choices=["wall", "cpu"], default="wall", help="time the update lines by wall or process CPU time"
    )
    args = parser.parse_args()
    set_clock(args.clock)

    torch.set_num_threads(args.threads)
    for line in machine_lines(torch.device(args.device)):
        print(line, flush=True)
    update_report(args)
    if args.only_update:
        return
    sb3_version = "not used"
    if not args.no_sb3:
        import stable_baselines3  # fail early, before our run, if the bench extra is missing

        sb3_version = stable_baselines3.__version__
    device = torch.cuda.get_device_name(0) if args.device == "cuda" else platform.processor() or platform.machine()
    print(f"env {args.env} (cap {args.cap}), hidden {args.hidden}, batch {args.batch}, device {args.device}: {device}")
    print(
        f"warm-up {args.warmup} steps (untimed), timed {args.steps} steps, torch {torch.__version__} "
        f"with {torch.get_num_threads()} thread(s), stable-baselines3 {sb3_version}, {os.cpu_count()} cores"
    )
    rows: list[tuple[str, int, float, float]] = []  # (side, specialists, aggregate steps/s, per CPU-second)
    for k in sorted({1, *args.stack}):
        print(f"ours x{k}: start ({load()})", flush=True)
        (wall, cpu), n_q = bench_ours(args, k)
        rows.append((f"ours x{k}", k, k * args.steps / wall, k * args.steps / cpu))
        print(
            f"ours x{k}: {n_q} Q-networks each, {wall:.1f} s wall: {k * args.steps / wall:.1f} steps/s aggregate, "
            f"{args.steps / wall:.1f} per specialist ({k * args.steps / cpu:.1f} per CPU-second) ({load()})",
            flush=True,
        )
        if args.processes > 1 and k >= args.processes:
            print(f"ours x{k} in {args.processes} processes: start ({load()})", flush=True)
            rate, per_cpu = bench_side_by_side(args, k, args.processes)
            rows.append((f"ours x{k} in {args.processes} processes", k, rate, per_cpu))
            print(
                f"ours x{k} in {args.processes} processes: {rate:.1f} steps/s aggregate, {rate / k:.1f} per specialist "
                f"({per_cpu:.1f} per CPU-second of its processes) ({load()})",
                flush=True,
            )
    if not args.no_sb3:
        print(f"sb3: start ({load()})", flush=True)
        wall, cpu = bench_sb3(args)
        rows.append(("sb3", 1, args.steps / wall, args.steps / cpu))
        print(
            f"sb3: 2 Q-networks, {wall:.1f} s wall: {args.steps / wall:.1f} steps/s ({args.steps / cpu:.1f} per CPU-second) ({load()})",
            flush=True,
        )

    one = rows[0][2]
    print("\n| run | specialists | aggregate steps/s | per specialist | vs one alone (aggregate) |")
    print("|---|---|---|---|---|")
    for side, k, rate, _ in rows:
        print(f"| {side} | {k} | {rate:.1f} | {rate / k:.1f} | {rate / one:.2f}x |")
    if not args.no_sb3:
        print(f"\nratio one of ours (4 Q-networks) / sb3 (2): {one / rows[-1][2]:.2f}")
    # An env x seed needs 2 specialists of paper_steps each; stacking k of them shares the
    # process among k / 2 such runs, so each costs 2 * paper_steps / (aggregate rate) of wall time.
    steps = 2 * args.paper_steps
    print(f"\nprojected hours for the specialists of one paper-scale env x seed ({steps / 1e6:g}M steps), amortised:")
    for side, k, rate, _ in rows:
        if side.startswith("ours"):
            print(f"  {side}: {steps / rate / 3600:.2f} h")


if __name__ == "__main__":
    main()
