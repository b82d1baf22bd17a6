"""Evaluating deterministic policies: undiscounted vector returns over several episodes.

All episodes run together: the active envs are stepped in a Python loop, but the actors are
called once per step. One policy is called on the stacked observations of its active envs;
several policies of one architecture (the children of one iteration) are called as one
`StackedActor` on the observations of all their envs, so K children x E episodes cost one
batched forward per step instead of K.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Sequence

import gymnasium as gym
import numpy as np
import torch

from pipeline.core.envs import reward_dim
from pipeline.core.nets import Actor, StackedActor
from pipeline.core.precision import frozen
from pipeline.core.seeding import derive_seeds

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


def actor_device(actor: torch.nn.Module) -> torch.device:
    """The device `actor` runs on: that of its first parameter, else of its first buffer (a
    TorchScript policy saved after `torch.jit.freeze` has no parameters: its weights are
    constants, and `ScriptedActor` holds the env's bounds as buffers), else the CPU."""
    first = next(itertools.chain(actor.parameters(), actor.buffers()), None)
    return torch.device("cpu") if first is None else first.device


def eval_seeds(run_seed: int, stream: int, policy_index: int, episodes: int) -> list[int]:
    """Env reset seeds for evaluating policy `policy_index`; `stream` separates extraction from
    the final re-evaluation so the latter sees fresh episodes."""
    return derive_seeds(run_seed, EVAL_TAG, stream, policy_index, n=episodes)


def evaluate_policy(actor: Actor, envs: list[gym.Env], seeds: list[int], precision: str = "fp32") -> EvalResult:
    """Run one episode per env (env i reset with seeds[i]) with deterministic actions.

    Episodes end at termination or at the envs' own step cap (truncation).
    """
    return evaluate_policies([actor], envs, [seeds], precision)[0]


@torch.no_grad()
def evaluate_policies(
    actors: Sequence[Actor], envs: Sequence[gym.Env], seeds: Sequence[Sequence[int]], precision: str = "fp32"
) -> list[EvalResult]:
    """Run policy i for one episode per seed in seeds[i], every episode of every policy at once.

    Episodes take the envs in order (policy 0's on the first len(seeds[0]) envs, ...), each
    reset with its own seed, so a policy's returns depend on its seeds alone, not on the other
    policies evaluated beside it (up to the float rounding of the batched forward, which
    differs from a lone actor's in the last bits). Several actors must share one architecture.
    precision "bf16" (resolved, pipeline.core.precision): the project's own actors run as
    bfloat16 copies made once here (imported TorchScript or torch.export ones stay fp32), the
    observations cast to bfloat16, the actions fp32. Returns one EvalResult per policy.
    """
    actors = [frozen(a, precision) for a in actors]
    slots = [(i, s) for i, policy_seeds in enumerate(seeds) for s in policy_seeds]
    if len(slots) > len(envs):
        raise ValueError(f"{len(slots)} episodes asked for but only {len(envs)} envs given")
    device = actor_device(actors[0])
    # One policy: called on its active envs' observations only (the unbatched code path, so a
    # lone policy's returns are bit for bit what they were before batching existed).
    stacked = StackedActor(actors).to(device) if len(actors) > 1 else None
    width = max(len(s) for s in seeds)
    column = [e for policy_seeds in seeds for e in range(len(policy_seeds))]  # episode index within its policy
    obs = [envs[n].reset(seed=int(s))[0] for n, (_, s) in enumerate(slots)]
    n_obj = reward_dim(envs[0])
    returns = [np.zeros((len(s), n_obj)) for s in seeds]
    samples = [0] * len(actors)
    active = list(range(len(slots)))
    while active:
        if stacked is None:
            batch = torch.as_tensor(np.stack([obs[n] for n in active]), dtype=torch.float32, device=device)
            actions = actors[0](batch).cpu().numpy()
        else:
            # Every env's latest observation (finished ones too: their actions are discarded),
            # so the batch keeps one (K, width) shape.
            grid = np.zeros((len(actors), width, obs[0].shape[0]), np.float32)
            for n, (i, _) in enumerate(slots):
                grid[i, column[n]] = obs[n]
            out = stacked(torch.as_tensor(grid, device=device)).cpu().numpy()
            actions = [out[slots[n][0], column[n]] for n in active]
        still = []
        for a, n in zip(actions, active):
            o, r, terminated, truncated, _ = envs[n].step(a)
            i = slots[n][0]
            returns[i][column[n]] += r
            samples[i] += 1
            obs[n] = o
            if not (terminated or truncated):
                still.append(n)
        active = still
    return [EvalResult(returns=r, env_samples=s) for r, s in zip(returns, samples)]
