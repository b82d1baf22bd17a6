"""Evaluating deterministic policies: undiscounted vector returns over several episodes.

All episodes of one policy run together: the active envs are stepped in a Python loop but
the actor is called once per step on the stacked observations of every active env.
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import torch

from pipeline.nets import Actor
from pipeline.seeding import derive_seeds

EVAL_TAG = 0x5EED_E7A1  # separates evaluation seeds from every other stream derived from a run seed


@dataclass(frozen=True)
class EvalResult:
    returns: np.ndarray  # (episodes, n_objectives) undiscounted return of each episode
    env_samples: int  # env steps spent

    @property
    def mean(self) -> np.ndarray:
        return self.returns.mean(axis=0)

    @property
    def std(self) -> np.ndarray:
        return self.returns.std(axis=0)


def eval_seeds(run_seed: int, stream: int, policy_index: int, episodes: int) -> list[int]:
    """Env reset seeds for evaluating policy `policy_index`; `stream` separates extraction from
    the final re-evaluation so the latter sees fresh episodes."""
    return derive_seeds(run_seed, EVAL_TAG, stream, policy_index, n=episodes)


@torch.no_grad()
def evaluate_policy(actor: Actor, envs: list[gym.Env], seeds: list[int]) -> EvalResult:
    """Run one episode per env (env i reset with seeds[i]) with deterministic actions.

    Episodes end at termination or at the envs' own step cap (truncation).
    """
    if len(seeds) > len(envs):
        raise ValueError(f"{len(seeds)} episodes asked for but only {len(envs)} envs given")
    n = len(seeds)
    device = next(actor.parameters()).device
    obs = [envs[i].reset(seed=int(seeds[i]))[0] for i in range(n)]
    n_obj = envs[0].unwrapped.reward_space.shape[0]
    returns = np.zeros((n, n_obj))
    active = list(range(n))
    samples = 0
    while active:
        batch = torch.as_tensor(np.stack([obs[i] for i in active]), dtype=torch.float32, device=device)
        actions = actor(batch).cpu().numpy()
        still = []
        for a, i in zip(actions, active):
            o, r, terminated, truncated, _ = envs[i].step(a)
            returns[i] += r
            samples += 1
            obs[i] = o
            if not (terminated or truncated):
                still.append(i)
        active = still
    return EvalResult(returns=returns, env_samples=samples)
