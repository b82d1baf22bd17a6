"""Train one Stable-Baselines3 TD3 specialist per objective of an MO-Gymnasium env and save them.

This is the "bring your own specialists" worked example (README, "Bring your own
specialists"): it plays the part of a user who already trained single-objective policies with
SB3. Specialist k is trained on objective k's reward alone (the env's reward vector weighted
by the one-hot vector e_k), with episodes capped like the pipeline's (750 steps by default).
The saved zips are what `presets/imported.yaml` imports:

    python examples/train_sb3_specialists.py --steps 100000 --out models
    mapex plan --from presets/imported.yaml && dvc repro

The objectives train side by side, one process and one torch thread each. Needs
stable-baselines3 (pip install -e ".[dev]" or ".[bench]"); the pipeline itself never imports it.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import time
from pathlib import Path


def train_one(env_id: str, objective: int, steps: int, seed: int, max_steps: int, net_arch, out: Path) -> str:
    import gymnasium as gym
    import mo_gymnasium as mo
    import numpy as np
    import torch
    from mo_gymnasium.wrappers import LinearReward
    from stable_baselines3 import TD3
    from stable_baselines3.common.noise import NormalActionNoise

    torch.set_num_threads(1)
    env = mo.make(env_id, max_episode_steps=max_steps)
    n_obj = env.unwrapped.reward_space.shape[0]
    weight = np.zeros(n_obj, dtype=np.float32)
    weight[objective] = 1.0
    env = LinearReward(env, weight=weight)  # the scalar reward SB3 trains on: objective k alone
    env = gym.wrappers.RecordEpisodeStatistics(env)
    act_dim = env.action_space.shape[0]
    model = TD3(
        "MlpPolicy",
        env,
        learning_starts=min(10_000, steps // 4),  # rl-zoo's HalfCheetah value
        action_noise=NormalActionNoise(np.zeros(act_dim), 0.1 * np.ones(act_dim)),
        buffer_size=max(steps, 1),
        policy_kwargs={"net_arch": list(net_arch)},
        seed=seed + 1000 * objective,
        device="cpu",
    )
    start = time.perf_counter()
    model.learn(total_timesteps=steps)
    path = out / f"td3_obj{objective}.zip"
    model.save(path)
    returns = [float(e["r"]) for e in list(model.ep_info_buffer)[-5:]]
    took = time.perf_counter() - start
    return f"objective {objective}: {path} ({steps} steps in {took:.0f} s; last training episodes' returns {returns})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--env", default="mo-halfcheetah-v5", help="MO-Gymnasium env id")
    parser.add_argument("--steps", type=int, default=100_000, help="env steps per specialist")
    parser.add_argument("--objectives", type=int, nargs="+", default=[0, 1], help="one specialist each")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-episode-steps", type=int, default=750)
    parser.add_argument(
        "--net-arch",
        type=int,
        nargs="+",
        default=[64, 64],
        help="hidden widths (SB3 TD3 default: 400 300; 64 64 keeps 100k steps within about 15 min here)",
    )
    parser.add_argument("--out", type=Path, default=Path("models"))
    parser.add_argument("--processes", type=int, default=2, help="objectives trained at once")
    a = parser.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    jobs = [(a.env, k, a.steps, a.seed, a.max_episode_steps, a.net_arch, a.out) for k in a.objectives]
    with mp.get_context("spawn").Pool(min(a.processes, len(jobs))) as pool:
        for line in pool.starmap(train_one, jobs):
            print(line, flush=True)


if __name__ == "__main__":
    main()
