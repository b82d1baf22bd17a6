"""Training single-objective TD3 specialists, with secondary critics (paper: "Secondary Critics").

`train_specialists` trains S specialists in lockstep in one process: the specialists of every
objective of a seed, or of several seeds. Each keeps its own env, replay buffer, RNG streams
and minibatch draws, so each is exactly the TD3 specialist it would be alone; only the
networks are stacked, so one batched update serves all of them (see pipeline/td3.py). S = 1
is one specialist on its own (`train_specialist`).

The loop prints nothing; progress goes through the `on_step` callback.

Devices: on a CPU the buffers are CPU tensors and minibatch rows are drawn with each
specialist's numpy generator (the same stream as its exploration noise). On CUDA the buffers
live on the GPU, rows are drawn on the GPU from a per-specialist torch generator, and the
update runs as captured CUDA graphs (`train_specialist.cuda_graphs`); the only per-step host
sync is reading the actions to step the envs. The two devices therefore draw different
(each reproducible) minibatches.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Callable, Sequence

import gymnasium as gym
import numpy as np
import torch

from pipeline.buffer import StackedReplay
from pipeline.envs import EnvSpec
from pipeline.nets import Actor, CriticEnsemble, StackedActor
from pipeline.params.train_specialist import TrainSpecialistParams
from pipeline.seeding import derive_seeds, torch_generator
from pipeline.td3 import GraphedUpdate, StackedTD3, TD3State, stacked_update


@dataclass
class EpisodeRecord:
    episode: int
    end_step: int  # global env step at which the episode ended (1-based count)
    length: int
    returns: np.ndarray  # (n_objectives,) undiscounted
    terminated: bool


@dataclass
class SpecialistResult:
    """What one trained specialist leaves behind (CPU modules, buffer rows oldest first)."""

    seed: int
    objective: int
    actor: Actor
    actor_target: Actor
    critic: CriticEnsemble
    critic_target: CriticEnsemble
    objectives: list[int]  # objectives its critic ensemble covers, in member order
    buffer: dict[str, np.ndarray]
    episodes: list[EpisodeRecord] = field(default_factory=list)


def covered_objectives(objective: int, n_objectives: int, secondary: bool) -> tuple[list[int], int]:
    """Objectives the critic ensemble covers, in member order, and the index of the primary in that list.

    With secondary critics the ensemble covers every objective 0..n-1; without, only `objective`.
    """
    if secondary:
        return list(range(n_objectives)), objective
    return [objective], 0


def init_td3(spec: EnvSpec, cfg: TrainSpecialistParams, objective: int, device: torch.device) -> TD3State:
    """One specialist's networks unstacked: the reference form that `td3.td3_update` trains
    (the tests check the stacked update against it)."""
    objectives, primary = covered_objectives(objective, spec.n_objectives, cfg.secondary_critics)
    actor = Actor(spec.obs_dim, spec.act_dim, cfg.hidden_sizes, spec.action_low, spec.action_high).to(device)
    critic = CriticEnsemble(spec.obs_dim, spec.act_dim, cfg.hidden_sizes, 2 * len(objectives)).to(device)
    return TD3State(
        actor=actor,
        actor_target=copy.deepcopy(actor).requires_grad_(False),
        critic=critic,
        critic_target=copy.deepcopy(critic).requires_grad_(False),
        actor_opt=torch.optim.Adam(actor.parameters(), lr=cfg.actor_lr, fused=True),
        critic_opt=torch.optim.Adam(critic.parameters(), lr=cfg.critic_lr, fused=True),
        objectives=objectives,
        primary=primary,
    )


def run_seeds(seed: int, objective: int) -> dict[str, int]:
    """The independent seeds of specialist (seed, objective): the same however many are stacked."""
    names = ("torch", "env", "space", "numpy", "noise", "cuda_rows")
    return dict(zip(names, derive_seeds(seed, objective, n=len(names))))


def init_stacked(spec: EnvSpec, cfg: TrainSpecialistParams, jobs: Sequence[tuple[int, int]], device: torch.device) -> StackedTD3:
    """Stacked networks of specialists `jobs` = [(seed, objective), ...], each initialised as it
    would be alone (torch seeded with its own seed, actor first, then its critics)."""
    actors, critics, reward_index, primary = [], [], [], []
    for s, (seed, objective) in enumerate(jobs):
        objectives, j = covered_objectives(objective, spec.n_objectives, cfg.secondary_critics)
        torch.manual_seed(run_seeds(seed, objective)["torch"])
        actors.append(Actor(spec.obs_dim, spec.act_dim, cfg.hidden_sizes, spec.action_low, spec.action_high))
        critics.append(CriticEnsemble(spec.obs_dim, spec.act_dim, cfg.hidden_sizes, 2 * len(objectives)))
        reward_index.append(objectives)
        primary.append(s * 2 * len(objectives) + 2 * j)
    actor = StackedActor(actors).to(device)
    critic = CriticEnsemble.stack(critics).to(device)
    # fused Adam: one kernel per parameter tensor (same update as the plain one). Captured CUDA
    # graphs need the optimizer's step counters on the device (capturable).
    graphs = device.type == "cuda" and cfg.cuda_graphs
    opt = dict(fused=True, capturable=True) if graphs else dict(fused=True)
    return StackedTD3(
        actor=actor,
        actor_target=copy.deepcopy(actor).requires_grad_(False),
        critic=critic,
        critic_target=copy.deepcopy(critic).requires_grad_(False),
        actor_opt=torch.optim.Adam(actor.parameters(), lr=cfg.actor_lr, **opt),
        critic_opt=torch.optim.Adam(critic.parameters(), lr=cfg.critic_lr, **opt),
        reward_index=torch.tensor(reward_index, dtype=torch.long, device=device),
        primary_members=torch.tensor(primary, dtype=torch.long, device=device),
    )


def exploration_actions(actor: StackedActor, obs: np.ndarray, noise_std: float, rngs: Sequence[np.random.Generator]) -> np.ndarray:
    """pi_s(s_s) plus Gaussian noise (std noise_std times the action half-range) per specialist,
    clipped to the bounds: obs (S, o) -> (S, a). Reading the actions is the step's one host sync."""
    device = actor.scale.device
    with torch.no_grad():
        a = actor(torch.as_tensor(obs, dtype=torch.float32, device=device).unsqueeze(1))[:, 0].cpu().numpy()
    scale = actor.scale[:, 0].cpu().numpy()
    centre = actor.centre[:, 0].cpu().numpy()
    for s, rng in enumerate(rngs):
        a[s] += rng.normal(0.0, noise_std, size=a.shape[1]).astype(np.float32) * scale[s]
    return np.clip(a, centre - scale, centre + scale).astype(np.float32)


class _Updater:
    """Draws each specialist's minibatch rows and smoothing noise and runs one stacked update."""

    def __init__(self, state: StackedTD3, buffer: StackedReplay, cfg: TrainSpecialistParams, seeds: list[dict[str, int]], rngs, device):
        self.state, self.buffer, self.cfg, self.rngs = state, buffer, cfg, rngs
        self.device = device
        s, b, act = state.n, cfg.batch_size, state.actor.scale.shape[-1]
        self.noise_gens = [torch_generator(x["noise"], device) for x in seeds]
        self.noise = torch.zeros(s, b, act, device=device)
        self.on_cuda = device.type == "cuda"
        if self.on_cuda:
            self.row_gens = [torch_generator(x["cuda_rows"], device) for x in seeds]
            self.idx = torch.zeros(s, b, dtype=torch.long, device=device)
        self.graphed: GraphedUpdate | None = None
        self.args = dict(gamma=cfg.gamma, tau=cfg.tau, policy_noise=cfg.policy_noise, noise_clip=cfg.noise_clip)

    def __call__(self, update_actor: bool) -> None:
        for s, g in enumerate(self.noise_gens):
            self.noise[s].normal_(generator=g)
        if self.on_cuda:
            for s, g in enumerate(self.row_gens):
                self.idx[s].random_(0, self.buffer.size, generator=g)
            idx = self.idx
        else:
            idx = torch.from_numpy(np.stack([rng.integers(0, self.buffer.size, size=self.cfg.batch_size) for rng in self.rngs]))
        if self.on_cuda and self.cfg.cuda_graphs:
            if self.graphed is None:
                self.graphed = GraphedUpdate(self.state, self.buffer.gather, self.idx, self.noise, **self.args)
            self.graphed(update_actor)
        else:
            stacked_update(self.state, self.buffer.gather(idx), self.noise, update_actor, **self.args)


def train_specialists(
    envs: Sequence[gym.Env],
    spec: EnvSpec,
    cfg: TrainSpecialistParams,
    jobs: Sequence[tuple[int, int]],
    device: torch.device,
    on_step: Callable[[int, list[EpisodeRecord | None]], None] | None = None,
) -> list[SpecialistResult]:
    """Train specialists jobs = [(seed, objective), ...] with TD3 for cfg.total_steps env steps
    each, in lockstep, specialist s on envs[s].

    Randomness: torch init, env resets, the start-up action sampler, exploration noise, batch
    rows and target smoothing noise are all seeded from (seed, objective) alone, so a
    specialist draws the same whatever else is stacked with it, and the same inputs give
    bitwise-identical results on a CPU (same thread count and library versions).
    """
    for seed, objective in jobs:
        if not 0 <= objective < spec.n_objectives:
            raise ValueError(f"objective {objective} out of range: env {spec.env_id} has {spec.n_objectives} objectives")
    if len(envs) != len(jobs):
        raise ValueError(f"{len(jobs)} specialists need as many envs, got {len(envs)}")
    n = len(jobs)
    seeds = [run_seeds(seed, objective) for seed, objective in jobs]
    state = init_stacked(spec, cfg, jobs, device)
    rngs = [np.random.default_rng(x["numpy"]) for x in seeds]
    for env, x in zip(envs, seeds):
        env.action_space.seed(x["space"])
    buffer = StackedReplay(n, cfg.buffer_size, spec.obs_dim, spec.act_dim, spec.n_objectives, device)
    update = _Updater(state, buffer, cfg, seeds, rngs, device)
    episodes: list[list[EpisodeRecord]] = [[] for _ in range(n)]

    obs = np.stack([env.reset(seed=x["env"])[0] for env, x in zip(envs, seeds)]).astype(np.float32)
    episode = np.zeros(n, np.int64)
    ep_step = np.zeros(n, np.int64)
    ep_return = np.zeros((n, spec.n_objectives))
    next_obs = np.zeros_like(obs)
    reward = np.zeros((n, spec.n_objectives), np.float32)
    terminated = np.zeros(n, bool)
    truncated = np.zeros(n, bool)
    n_updates = 0
    for t in range(cfg.total_steps):
        if t < cfg.learning_starts:
            actions = np.stack([np.asarray(env.action_space.sample(), dtype=np.float32) for env in envs])
        else:
            actions = exploration_actions(state.actor, obs, cfg.exploration_noise, rngs)
        for s, env in enumerate(envs):
            o, r, terminated[s], truncated[s], _ = env.step(actions[s])
            next_obs[s], reward[s] = o, r
        buffer.add(obs, actions, reward, next_obs, terminated, truncated, episode, ep_step)
        ep_return += reward
        ep_step += 1
        obs = next_obs.copy()
        records: list[EpisodeRecord | None] = [None] * n
        for s in np.flatnonzero(terminated | truncated):
            records[s] = EpisodeRecord(int(episode[s]), t + 1, int(ep_step[s]), ep_return[s].copy(), bool(terminated[s]))
            episodes[s].append(records[s])
            obs[s] = envs[s].reset()[0]
            episode[s] += 1
            ep_step[s] = 0
            ep_return[s] = 0.0
        if t >= cfg.learning_starts:
            n_updates += 1
            update(update_actor=n_updates % cfg.policy_freq == 0)
        if on_step is not None:
            on_step(t + 1, records)

    e = state.critic.n_members // n
    return [
        SpecialistResult(
            seed=seed,
            objective=objective,
            actor=state.actor.unstack(s),
            actor_target=state.actor_target.unstack(s),
            critic=state.critic.subset(s * e, (s + 1) * e).cpu(),
            critic_target=state.critic_target.subset(s * e, (s + 1) * e).cpu().requires_grad_(False),
            objectives=state.reward_index[s].tolist(),
            buffer=buffer.chronological(s),
            episodes=episodes[s],
        )
        for s, (seed, objective) in enumerate(jobs)
    ]


def train_specialist(
    env: gym.Env,
    spec: EnvSpec,
    cfg: TrainSpecialistParams,
    objective: int,
    seed: int,
    device: torch.device,
    on_step: Callable[[int, EpisodeRecord | None], None] | None = None,
) -> SpecialistResult:
    """One specialist alone: `train_specialists` with S = 1."""
    step = None if on_step is None else (lambda t, records: on_step(t, records[0]))
    return train_specialists([env], spec, cfg, [(seed, objective)], device, step)[0]
