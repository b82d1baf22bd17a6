"""Speed of our specialist training against stable-baselines3's TD3, on the same machine.

Trains (a) our TD3 specialist with secondary critics (on a 2-objective env: 2 objectives x 2
heads = 4 Q-networks) and (b) stable-baselines3's TD3 (2 Q-networks) on the same env reduced
to one objective, with the same network widths, batch size, warm-up and thread count, and
reports env steps per second after the warm-up (each such step does one gradient update)
and the ratio ours / SB3. The goal: ours >= 0.8x SB3 while training twice the critics.

    pip install -e ".[bench]"          # stable-baselines3
    python benchmarks/bench_specialist.py                    # defaults: 2000 warm-up + 3000 timed steps
    python benchmarks/bench_specialist.py --steps 10000 --threads 2 --hidden 256 256

Warm-up steps (uniform random actions, no updates) are not timed. Both runs use CPU. Each
side reports steps per wall-second and per CPU-second of its process; on a shared machine the
second is the steadier figure. --repeats N alternates the order of the sides and reports the
median ratio.
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

from pipeline.envs import env_spec, make_env  # noqa: E402
from pipeline.params.train_specialist import TrainSpecialistParams  # noqa: E402
from pipeline.specialist import train_specialist  # noqa: E402


def load() -> str:
    return "load average {:.2f} {:.2f} {:.2f}".format(*os.getloadavg())


def clocks() -> tuple[float, float]:
    """(wall, CPU time of this process): on a shared machine the CPU time is the steadier one."""
    return time.perf_counter(), time.process_time()


def bench_ours(args: argparse.Namespace) -> tuple[tuple[float, float], int]:
    """Our specialist; returns ((wall s, CPU s) of the timed steps, number of Q-networks trained)."""
    cfg = TrainSpecialistParams(
        total_steps=args.warmup + args.steps,
        learning_starts=args.warmup,
        buffer_size=args.warmup + args.steps,
        batch_size=args.batch,
        hidden_sizes=args.hidden,
        secondary_critics=not args.no_secondary,
        device="cpu",
    )
    env = make_env(args.env, args.cap)
    spec = env_spec(env, args.env, args.cap)
    start: list[tuple[float, float]] = []

    def on_step(t: int, _record) -> None:
        if t == args.warmup:  # the last warm-up step is done; updates start with the next one
            start.append(clocks())

    result = train_specialist(env, spec, cfg, args.objective, args.seed, torch.device("cpu"), on_step=on_step)
    end = clocks()
    env.close()
    return (end[0] - start[0][0], end[1] - start[0][1]), result.state.critic.n_members


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
        device="cpu",
        verbose=0,
    )
    model.learn(total_timesteps=args.warmup + args.steps, callback=StartTimer())
    end = clocks()
    env.close()
    return end[0] - start[0][0], end[1] - start[0][1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="mo-halfcheetah-v5", help="MO-Gymnasium env id")
    parser.add_argument("--cap", type=int, default=750, help="episode cap (max_episode_steps)")
    parser.add_argument("--objective", type=int, default=0, help="our specialist's objective; SB3 gets this objective alone")
    parser.add_argument("--warmup", type=int, default=2000, help="random-action steps before updates (not timed)")
    parser.add_argument("--steps", type=int, default=3000, help="timed steps after the warm-up, one update each")
    parser.add_argument("--batch", type=int, default=256, help="minibatch size")
    parser.add_argument("--hidden", type=int, nargs="+", default=[256, 256], help="hidden widths of actor and critics")
    parser.add_argument("--threads", type=int, default=1, help="torch intra-op threads, the same for both")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-secondary", action="store_true", help="ours without secondary critics (2 Q-networks)")
    parser.add_argument("--only", choices=["ours", "sb3"], help="run one side only")
    parser.add_argument("--repeats", type=int, default=1, help="passes over both sides, in alternating order")
    args = parser.parse_args()

    torch.set_num_threads(args.threads)
    sb3_version = "not used"
    if args.only != "ours":
        import stable_baselines3  # fail early, before our run, if the bench extra is missing

        sb3_version = stable_baselines3.__version__

    print(f"env {args.env} (cap {args.cap}), objective {args.objective}, hidden {args.hidden}, batch {args.batch}")
    print(f"warm-up {args.warmup} steps (untimed), timed {args.steps} steps, torch {torch.__version__} "
          f"with {torch.get_num_threads()} thread(s), stable-baselines3 {sb3_version}, "
          f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores")
    sides = [args.only] if args.only else ["ours", "sb3"]
    rates: dict[str, list[tuple[float, float]]] = {side: [] for side in sides}
    for rep in range(args.repeats):
        # Alternate the order so that a drift in the machine's load favours neither side.
        for side in sides if rep % 2 == 0 else sides[::-1]:
            print(f"{side}: start ({load()})", flush=True)
            if side == "ours":
                (wall, cpu), n_q = bench_ours(args)
            else:
                (wall, cpu), n_q = bench_sb3(args), 2
            rates[side].append((args.steps / wall, args.steps / cpu))
            print(f"{side}: {n_q} Q-networks, {wall:.1f} s wall, {cpu:.1f} s CPU: {args.steps / wall:.1f} steps/s "
                  f"({args.steps / cpu:.1f} per CPU-second) ({load()})", flush=True)
    if len(sides) == 2:
        wall_ratio = float(np.median([o[0] / b[0] for o, b in zip(rates["ours"], rates["sb3"])]))
        cpu_ratio = float(np.median([o[1] / b[1] for o, b in zip(rates["ours"], rates["sb3"])]))
        what = "" if args.repeats == 1 else f"median over {args.repeats} passes, "
        print(f"ratio ours / sb3 ({what}goal >= 0.80): {wall_ratio:.2f} in steps/s, {cpu_ratio:.2f} per CPU-second")


if __name__ == "__main__":
    main()
