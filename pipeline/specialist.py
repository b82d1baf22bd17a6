"""Training one single-objective TD3 specialist, with secondary critics (paper: "Secondary Critics").

`train_specialist` runs the env loop and returns everything a stage saves: the actor and its
target, the critic ensemble and its target, the replay buffer (full reward vectors) and the
per-episode returns. It prints nothing; progress goes through the `on_step` callback.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Callable

import gymnasium as gym
import numpy as np
import torch

from pipeline.buffer import ReplayBuffer
from pipeline.envs import EnvSpec
from pipeline.nets import Actor, CriticEnsemble
from pipeline.params.train_specialist import TrainSpecialistParams
from pipeline.seeding import derive_seeds, torch_generator
from pipeline.td3 import TD3State, td3_update


@dataclass
class EpisodeRecord:
    episode: int
    end_step: int  # global env step at which the episode ended (1-based count)
    length: int
    returns: np.ndarray  # (n_objectives,) undiscounted
    terminated: bool


@dataclass
class SpecialistResult:
    state: TD3State
    buffer: ReplayBuffer
    episodes: list[EpisodeRecord] = field(default_factory=list)


def covered_objectives(objective: int, n_objectives: int, secondary: bool) -> tuple[list[int], int]:
    """Objectives the critic ensemble covers, in member order, and the index of the primary in that list.

    With secondary critics the ensemble covers every objective 0..n-1; without, only `objective`.
    """
    if secondary:
        return list(range(n_objectives)), objective
    return [objective], 0


def init_td3(spec: EnvSpec, cfg: TrainSpecialistParams, objective: int, device: torch.device) -> TD3State:
    objectives, primary = covered_objectives(objective, spec.n_objectives, cfg.secondary_critics)
    actor = Actor(spec.obs_dim, spec.act_dim, cfg.hidden_sizes, spec.action_low, spec.action_high).to(device)
    critic = CriticEnsemble(spec.obs_dim, spec.act_dim, cfg.hidden_sizes, 2 * len(objectives)).to(device)
    actor_target = copy.deepcopy(actor).requires_grad_(False)
    critic_target = copy.deepcopy(critic).requires_grad_(False)
    return TD3State(
        actor=actor,
        actor_target=actor_target,
        critic=critic,
        critic_target=critic_target,
        # fused: one kernel per parameter tensor instead of a dozen element-wise ops
        # (same Adam update; about 7% of an update's time on a CPU).
        actor_opt=torch.optim.Adam(actor.parameters(), lr=cfg.actor_lr, fused=True),
        critic_opt=torch.optim.Adam(critic.parameters(), lr=cfg.critic_lr, fused=True),
        objectives=objectives,
        primary=primary,
    )


def exploration_action(
    actor: Actor, obs: np.ndarray, noise_std: float, rng: np.random.Generator, device: torch.device
) -> np.ndarray:
    """pi(s) plus Gaussian noise of std noise_std times the action half-range, clipped to bounds."""
    with torch.no_grad():
        a = actor(torch.as_tensor(obs, dtype=torch.float32, device=device).unsqueeze(0))[0].cpu().numpy()
    scale = actor.scale.cpu().numpy()
    centre = actor.centre.cpu().numpy()
    a = a + rng.normal(0.0, noise_std, size=a.shape).astype(np.float32) * scale
    return np.clip(a, centre - scale, centre + scale).astype(np.float32)


def train_specialist(
    env: gym.Env,
    spec: EnvSpec,
    cfg: TrainSpecialistParams,
    objective: int,
    seed: int,
    device: torch.device,
    on_step: Callable[[int, EpisodeRecord | None], None] | None = None,
) -> SpecialistResult:
    """Train specialist `objective` with TD3 for cfg.total_steps env steps.

    Randomness: torch init, env resets, the start-up action sampler, exploration noise, batch
    indices and target smoothing noise are all seeded from (seed, objective), so the same
    inputs give bitwise-identical results on CPU.
    """
    if not 0 <= objective < spec.n_objectives:
        raise ValueError(f"objective {objective} out of range: env {spec.env_id} has {spec.n_objectives} objectives")
    s_torch, s_env, s_space, s_np, s_noise = derive_seeds(seed, objective, n=5)
    torch.manual_seed(s_torch)
    state = init_td3(spec, cfg, objective, device)
    rng = np.random.default_rng(s_np)
    gen = torch_generator(s_noise, device)
    env.action_space.seed(s_space)
    buffer = ReplayBuffer(cfg.buffer_size, spec.obs_dim, spec.act_dim, spec.n_objectives)
    result = SpecialistResult(state=state, buffer=buffer)

    obs, _ = env.reset(seed=s_env)
    episode, ep_step, ep_return = 0, 0, np.zeros(spec.n_objectives)
    n_updates = 0
    for t in range(cfg.total_steps):
        if t < cfg.learning_starts:
            action = np.asarray(env.action_space.sample(), dtype=np.float32)
        else:
            action = exploration_action(state.actor, obs, cfg.exploration_noise, rng, device)
        next_obs, reward, terminated, truncated, _ = env.step(action)
        reward = np.asarray(reward, dtype=np.float32)
        buffer.add(obs, action, reward, next_obs, terminated, truncated, episode, ep_step)
        ep_return += reward
        ep_step += 1
        obs = next_obs
        record = None
        if terminated or truncated:
            record = EpisodeRecord(episode, t + 1, ep_step, ep_return.copy(), bool(terminated))
            result.episodes.append(record)
            obs, _ = env.reset()
            episode, ep_step, ep_return = episode + 1, 0, np.zeros(spec.n_objectives)
        if t >= cfg.learning_starts:
            batch = buffer.sample(cfg.batch_size, rng, device)
            n_updates += 1
            td3_update(
                state,
                batch,
                update_actor=n_updates % cfg.policy_freq == 0,
                gamma=cfg.gamma,
                tau=cfg.tau,
                policy_noise=cfg.policy_noise,
                noise_clip=cfg.noise_clip,
                generator=gen,
            )
        if on_step is not None:
            on_step(t + 1, record)
    return result
