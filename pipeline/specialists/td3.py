"""TD3 updates for a specialist and its secondary critics, as small composable pieces.

Two forms of the same update live here. `td3_update` trains one specialist (the plain,
readable reference; post-hoc critic fitting reuses its pieces). `stacked_update` trains S
specialists at once, their actors and critic ensembles stacked along a leading dimension,
each on its own minibatch and noise: per specialist it is exactly `td3_update` (the losses
are sums of per-specialist losses over disjoint parameters, and Adam is elementwise), only
with S times fewer kernel launches. On CUDA, `GraphedUpdate` replays `stacked_update` as two
captured CUDA graphs, so an update costs a few launches instead of hundreds.

Specialist k's actor ascends only its primary critic Q^(k)_k (head 0, as in TD3). Every
critic in the ensemble (primary and secondary) regresses onto the same TD3 target rule:
y_m = r_m + gamma * (1 - terminated) * min_h Q'_{m,h}(s', clip(pi'(s') + clip(noise))),
computed with the specialist's own target policy (paper, section "Secondary Critics").
A truncated (time-limit) transition is not terminal, so the target bootstraps through it.

Also here: the builders of a specialist's networks (`init_td3` unstacked, `init_stacked` and
`stack_td3` stacked; `covered_objectives`, `run_seeds`), and `Updater`, one update of a
training run (each specialist's minibatch rows and smoothing noise, then `stacked_update` or
its graphs). The lockstep specialists (pipeline/specialists/td3_training.py) and the TD3 agent
of PDERL and MOPDERL (pipeline/specialists/td3_learner.py) both build on them.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import torch
from torch import nn

from pipeline.core.buffer import Batch, StackedReplay
from pipeline.core.envs import EnvSpec
from pipeline.core.nets import Actor, CriticEnsemble, StackedActor
from pipeline.core.optim import adam_step, clear_grads
from pipeline.core.precision import compute
from pipeline.core.seeding import derive_seeds, torch_generator
from pipeline.params.td3 import TD3Params


@dataclass
class TD3State:
    """Networks and optimizers of one specialist under training."""

    actor: Actor
    actor_target: Actor
    critic: CriticEnsemble
    critic_target: CriticEnsemble
    actor_opt: torch.optim.Optimizer
    critic_opt: torch.optim.Optimizer
    objectives: list[int]  # objectives covered by the ensemble, in member order
    primary: int  # index j into `objectives` of the specialist's own objective


def smoothed_target_action(
    actor_target: Actor, next_obs: torch.Tensor, policy_noise: float, noise_clip: float, generator: torch.Generator
) -> torch.Tensor:
    """pi'(s') plus clipped Gaussian noise (scaled by the action half-range), kept in bounds."""
    a = actor_target(next_obs)
    noise = torch.randn(a.shape, generator=generator, device=a.device, dtype=a.dtype) * policy_noise
    noise = noise.clamp(-noise_clip, noise_clip) * actor_target.scale
    low = actor_target.centre - actor_target.scale
    high = actor_target.centre + actor_target.scale
    return torch.max(torch.min(a + noise, high), low)


def td3_targets(
    critic_target: CriticEnsemble,
    next_obs: torch.Tensor,
    next_action: torch.Tensor,
    reward: torch.Tensor,
    terminated: torch.Tensor,
    gamma: float,
) -> torch.Tensor:
    """Bellman targets for every covered objective -> (n_obj, B).

    reward: (B, n_obj) already restricted to the covered objectives; terminated: (B,).
    """
    with torch.no_grad():
        q_next = critic_target.twin_min(next_obs, next_action)  # (n_obj, B)
        return reward.T + gamma * (1.0 - terminated).unsqueeze(0) * q_next


def critic_loss(critic: CriticEnsemble, obs: torch.Tensor, action: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """Sum over members of each member's MSE to its objective's target (targets: (n_obj, B)).

    Summing (not averaging) over members gives each member the same gradient it would get
    trained alone, so adding secondary critics does not slow the primary one down.
    """
    q = critic(obs, action)  # (E, B)
    y = targets.repeat_interleave(2, dim=0)  # (E, B): both heads of objective j share target j
    return ((q - y) ** 2).mean(dim=1).sum()


def actor_loss(actor: Actor, critic: CriticEnsemble, obs: torch.Tensor, member: int) -> torch.Tensor:
    """Deterministic policy gradient loss on one critic member: -mean Q_member(s, pi(s))."""
    return -critic.member(obs, actor(obs), member).mean()


@torch.no_grad()
def polyak_update(online: nn.Module, target: nn.Module, tau: float) -> None:
    """target <- (1 - tau) * target + tau * online, parameter by parameter."""
    t_params = list(target.parameters())
    torch._foreach_lerp_(t_params, list(online.parameters()), tau)


def td3_update(
    state: TD3State,
    batch: Batch,
    update_actor: bool,
    gamma: float,
    tau: float,
    policy_noise: float,
    noise_clip: float,
    generator: torch.Generator,
) -> dict[str, torch.Tensor]:
    """One TD3 step: all critics on `batch`; if `update_actor`, the actor and both targets too."""
    reward = batch.reward[:, state.objectives]
    with torch.no_grad():
        next_a = smoothed_target_action(state.actor_target, batch.next_obs, policy_noise, noise_clip, generator)
    y = td3_targets(state.critic_target, batch.next_obs, next_a, reward, batch.terminated, gamma)
    loss_q = critic_loss(state.critic, batch.obs, batch.action, y)
    state.critic_opt.zero_grad(set_to_none=True)
    loss_q.backward()
    state.critic_opt.step()
    metrics = {"critic_loss": loss_q.detach()}
    if update_actor:
        # The actor step needs dQ/da only: with the critic frozen, backward skips the critic
        # weight gradients (which the actor optimizer would never use anyway).
        state.critic.requires_grad_(False)
        try:
            loss_pi = actor_loss(state.actor, state.critic, batch.obs, member=2 * state.primary)
            state.actor_opt.zero_grad(set_to_none=True)
            loss_pi.backward()
        finally:
            state.critic.requires_grad_(True)
        state.actor_opt.step()
        polyak_update(state.critic, state.critic_target, tau)
        polyak_update(state.actor, state.actor_target, tau)
        metrics["actor_loss"] = loss_pi.detach()
    return metrics


# ---------------------------------------------------------------- S specialists at once


@dataclass
class StackedTD3:
    """Networks and optimizers of S specialists trained in lockstep (one stacked set)."""

    actor: StackedActor
    actor_target: StackedActor
    critic: CriticEnsemble  # S groups of 2 * n_cov members, group s = specialist s
    critic_target: CriticEnsemble
    actor_opt: torch.optim.Optimizer
    critic_opt: torch.optim.Optimizer
    reward_index: torch.Tensor  # (S, n_cov) long: objective behind each covered slot
    primary_members: torch.Tensor  # (S,) long: member index of each specialist's primary head 0

    @property
    def n(self) -> int:
        return self.reward_index.shape[0]


def stacked_targets(
    state: StackedTD3,
    batch: Batch,
    noise: torch.Tensor,
    gamma: float,
    policy_noise: float,
    noise_clip: float,
    precision: str = "fp32",
) -> torch.Tensor:
    """TD3 targets of every covered objective of every specialist -> (S, n_cov, B).

    batch fields carry a leading S; noise (S, B, act) is standard normal, drawn by the caller
    from each specialist's own generator (so the draws do not depend on how many are stacked).
    precision bf16: the target networks' forward passes under autocast; the smoothing noise,
    the next action and the targets themselves are fp32 (pipeline.core.precision).
    """
    device = batch.obs.device
    with torch.no_grad():
        with compute(precision, device):
            a = state.actor_target(batch.next_obs)
        scale, centre = state.actor_target.scale, state.actor_target.centre
        eps = (noise * policy_noise).clamp(-noise_clip, noise_clip) * scale
        next_a = torch.max(torch.min(a + eps, centre + scale), centre - scale)
        s, n_cov = state.reward_index.shape
        with compute(precision, device):
            q_next = state.critic_target.grouped(batch.next_obs, next_a)  # (S * 2 * n_cov, B)
        q_next = q_next.view(s, n_cov, 2, -1).amin(dim=2)
        reward = batch.reward.gather(2, state.reward_index.unsqueeze(1).expand(-1, batch.reward.shape[1], -1))
        return reward.transpose(1, 2) + gamma * (1.0 - batch.terminated).unsqueeze(1) * q_next


def stacked_critic_step(
    state: StackedTD3,
    batch: Batch,
    noise: torch.Tensor,
    gamma: float,
    policy_noise: float,
    noise_clip: float,
    precision: str = "fp32",
) -> torch.Tensor:
    """One Adam step of every critic of every specialist; returns the summed loss (a tensor).
    precision bf16: the critics' forward under autocast (backward outside it), the loss fp32."""
    y = stacked_targets(state, batch, noise, gamma, policy_noise, noise_clip, precision)  # (S, n_cov, B)
    with compute(precision, batch.obs.device):
        q = state.critic.grouped(batch.obs, batch.action)  # (S * 2 * n_cov, B)
    y = y.repeat_interleave(2, dim=1).reshape(q.shape)  # both heads of an objective share its target
    loss = ((q - y) ** 2).mean(dim=1).sum()
    clear_grads(state.critic_opt)
    loss.backward()
    adam_step(state.critic_opt)
    return loss.detach()


def stacked_actor_step(state: StackedTD3, obs: torch.Tensor, tau: float, precision: str = "fp32") -> torch.Tensor:
    """Each actor ascends its own primary critic on its own states (S, B, o); then Polyak (in
    fp32 whatever the precision: the targets move by tau = 0.005 of the gap, below bf16's resolution)."""
    state.critic.requires_grad_(False)  # dQ/da only (see td3_update)
    try:
        with compute(precision, obs.device):
            q = state.critic.grouped(obs, state.actor(obs), members=state.primary_members)  # (S, B)
        loss = -q.mean(dim=1).sum()
        clear_grads(state.actor_opt)
        loss.backward()
    finally:
        state.critic.requires_grad_(True)
    adam_step(state.actor_opt)
    polyak_update(state.critic, state.critic_target, tau)
    polyak_update(state.actor, state.actor_target, tau)
    return loss.detach()


def stacked_update(
    state: StackedTD3,
    batch: Batch,
    noise: torch.Tensor,
    update_actor: bool,
    gamma: float,
    tau: float,
    policy_noise: float,
    noise_clip: float,
    precision: str = "fp32",
) -> dict[str, torch.Tensor]:
    """One TD3 step of S specialists: `td3_update` for each, batched (see the module docstring);
    precision: "fp32", or "bf16" for the networks' forward passes (pipeline.core.precision)."""
    metrics = {"critic_loss": stacked_critic_step(state, batch, noise, gamma, policy_noise, noise_clip, precision)}
    if update_actor:
        metrics["actor_loss"] = stacked_actor_step(state, batch.obs, tau, precision)
    return metrics


class GraphedUpdate:
    """`stacked_update` on CUDA as two captured graphs: the critic step, and the actor step
    with the Polyak updates. Replaying a graph launches the whole step at once, which is what
    makes small (batch 256) updates fast on a GPU: eager PyTorch spends its time launching
    hundreds of tiny kernels, not computing.

    Static inputs: `idx` (S, B) minibatch rows and `noise` (S, B, act) target-smoothing noise,
    filled in place by the caller before each replay (drawn on the device from each
    specialist's generator: no host sync). The minibatch is gathered inside the graph from the
    device-resident buffer `rows` (S, capacity, F) via `gather(idx) -> Batch`. The optimizers
    must be built with capturable=True.
    """

    def __init__(
        self,
        state: StackedTD3,
        gather,
        idx: torch.Tensor,
        noise: torch.Tensor,
        gamma: float,
        tau: float,
        policy_noise: float,
        noise_clip: float,
        warmup: int = 3,
        precision: str = "fp32",
    ):
        self.state, self.gather, self.idx, self.noise = state, gather, idx, noise
        self.args = (gamma, policy_noise, noise_clip, precision)
        self.tau, self.precision = tau, precision
        self.obs = torch.zeros(idx.shape[0], idx.shape[1], state.actor.weights[0].shape[1], device=idx.device)
        if state.actor_opt.state or state.critic_opt.state:
            raise RuntimeError("GraphedUpdate must be built before the first update (fresh optimizers)")
        params = [
            p.data for m in (state.actor, state.actor_target, state.critic, state.critic_target) for p in m.parameters()
        ]
        saved = [p.clone() for p in params]
        # Capture needs a few eager runs on a side stream first (allocator and library warm-up).
        # They are real updates, so the parameters are restored afterwards and the optimizer
        # state they created is zeroed, which is exactly Adam's fresh state (step 0, zero moments).
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            for _ in range(warmup):
                self._critic()
                self._actor()
        torch.cuda.current_stream().wait_stream(side)
        with torch.no_grad():
            for p, v in zip(params, saved):
                p.copy_(v)
            for opt in (state.actor_opt, state.critic_opt):
                for per_param in opt.state.values():
                    for v in per_param.values():
                        if torch.is_tensor(v):
                            v.zero_()
        state.critic_opt.zero_grad(set_to_none=True)
        state.actor_opt.zero_grad(set_to_none=True)
        self.critic_graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.critic_graph):
            self._critic()
        self.actor_graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.actor_graph):
            self._actor()

    def _critic(self) -> None:
        batch = self.gather(self.idx)
        self.obs.copy_(batch.obs)
        stacked_critic_step(self.state, batch, self.noise, *self.args)

    def _actor(self) -> None:
        stacked_actor_step(self.state, self.obs, self.tau, self.precision)

    def __call__(self, update_actor: bool) -> None:
        self.critic_graph.replay()
        if update_actor:
            self.actor_graph.replay()


# ---------------------------------------------------------------- building the networks


def covered_objectives(objective: int, n_objectives: int, secondary: bool) -> tuple[list[int], int]:
    """Objectives the critic ensemble covers, in member order, and the index of the primary in that list.

    With secondary critics the ensemble covers every objective 0..n-1; without, only `objective`.
    """
    if secondary:
        return list(range(n_objectives)), objective
    return [objective], 0


def init_td3(spec: EnvSpec, cfg: TD3Params, objective: int, device: torch.device) -> TD3State:
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


def init_stacked(spec: EnvSpec, cfg: TD3Params, jobs: Sequence[tuple[int, int]], device: torch.device) -> StackedTD3:
    """Stacked networks of specialists `jobs` = [(seed, objective), ...], each initialised as it
    would be alone (torch seeded with its own seed, actor first, then its critics). With
    td3.shared_init every objective's networks of a seed are initialised from objective 0's seed,
    so they start equal (a deviation from the paper, for weight-space interpolation); only the
    initial weights: the other streams of `run_seeds` stay the objective's own."""
    actors, critics, covered, primary = [], [], [], []
    for seed, objective in jobs:
        objectives, j = covered_objectives(objective, spec.n_objectives, cfg.secondary_critics)
        torch.manual_seed(run_seeds(seed, 0 if cfg.shared_init else objective)["torch"])
        actors.append(Actor(spec.obs_dim, spec.act_dim, cfg.hidden_sizes, spec.action_low, spec.action_high))
        critics.append(CriticEnsemble(spec.obs_dim, spec.act_dim, cfg.hidden_sizes, 2 * len(objectives)))
        covered.append(objectives)
        primary.append(j)
    return stack_td3(cfg, actors, critics, covered, primary, device)


def stack_td3(
    cfg: TD3Params,
    actors: Sequence[Actor],
    critics: Sequence[CriticEnsemble],
    covered: Sequence[Sequence[int]],
    primary: Sequence[int],
    device: torch.device,
    actor_targets: Sequence[Actor] | None = None,
    critic_targets: Sequence[CriticEnsemble] | None = None,
) -> StackedTD3:
    """S specialists' networks stacked (copies; targets copies of the online nets unless given)
    with fresh optimizers. covered[s]: the objectives specialist s's ensemble covers, in member
    order; primary[s]: the index of its own objective in that list."""
    actor = StackedActor(actors).to(device)
    critic = CriticEnsemble.stack(critics).to(device)
    actor_target = copy.deepcopy(actor) if actor_targets is None else StackedActor(actor_targets).to(device)
    critic_target = copy.deepcopy(critic) if critic_targets is None else CriticEnsemble.stack(critic_targets).to(device)
    sizes = {2 * len(c) for c in covered}
    if len(sizes) != 1 or [c.n_members for c in critics] != [2 * len(c) for c in covered]:
        raise ValueError(
            f"stacked specialists need critic ensembles of one size, 2 members per covered objective: {list(covered)}"
        )
    e = sizes.pop()
    # fused Adam: one kernel per parameter tensor (same update as the plain one). Captured CUDA
    # graphs need the optimizer's step counters on the device (capturable).
    graphs = device.type == "cuda" and cfg.cuda_graphs
    opt = dict(fused=True, capturable=True) if graphs else dict(fused=True)
    return StackedTD3(
        actor=actor,
        actor_target=actor_target.requires_grad_(False),
        critic=critic,
        critic_target=critic_target.requires_grad_(False),
        actor_opt=torch.optim.Adam(actor.parameters(), lr=cfg.actor_lr, **opt),
        critic_opt=torch.optim.Adam(critic.parameters(), lr=cfg.critic_lr, **opt),
        reward_index=torch.tensor([list(c) for c in covered], dtype=torch.long, device=device),
        primary_members=torch.tensor([s * e + 2 * j for s, j in enumerate(primary)], dtype=torch.long, device=device),
    )


def unstack_actor(actor: StackedActor, s: int) -> Actor:
    """Actor s of a stacked set as a CPU `Actor`, leaving torch's global RNG as it was (building
    an `Actor` draws its throwaway initial weights from it)."""
    with torch.random.fork_rng(devices=[]):
        return actor.unstack(s)


# ---------------------------------------------------------------- one update of a training run


class Updater:
    """Draws each specialist's minibatch rows and smoothing noise and runs one stacked update
    in `precision` ("fp32" or "bf16", resolved: pipeline.core.precision)."""

    def __init__(
        self,
        state: StackedTD3,
        buffer: StackedReplay,
        cfg: TD3Params,
        seeds: list[dict[str, int]],
        rngs,
        device,
        precision: str = "fp32",
    ):
        self.state, self.buffer, self.cfg, self.rngs = state, buffer, cfg, rngs
        self.device = device
        s, b, act = state.n, cfg.batch_size, state.actor.scale.shape[-1]
        self.noise_gens = [torch_generator(x["noise"], device) for x in seeds]
        self.noise = torch.zeros(s, b, act, device=device)
        self.on_cuda = device.type == "cuda"
        if self.on_cuda:
            self.row_gens = [torch_generator(x["cuda_rows"], device) for x in seeds]
            self.idx = torch.zeros(s, b, dtype=torch.long, device=device)
        self.graphs = self.on_cuda and cfg.cuda_graphs
        self.graphed: GraphedUpdate | None = None
        self.args = dict(
            gamma=cfg.gamma, tau=cfg.tau, policy_noise=cfg.policy_noise, noise_clip=cfg.noise_clip, precision=precision
        )
        self.precision = precision
        # the latest critic and actor losses (eager updates only: a captured graph keeps its own)
        self.metrics: dict[str, torch.Tensor] = {}

    def graph(self) -> GraphedUpdate:
        """The captured update (CUDA graphs), captured on first use: it needs fresh optimizers."""
        if self.graphed is None:
            self.graphed = GraphedUpdate(self.state, self.buffer.gather, self.idx, self.noise, **self.args)
        return self.graphed

    def __call__(self, update_actor: bool) -> None:
        for s, g in enumerate(self.noise_gens):
            self.noise[s].normal_(generator=g)
        if self.on_cuda:
            for s, g in enumerate(self.row_gens):
                self.idx[s].random_(0, self.buffer.size, generator=g)
            idx = self.idx
        else:
            idx = torch.from_numpy(
                np.stack([rng.integers(0, self.buffer.size, size=self.cfg.batch_size) for rng in self.rngs])
            )
        if self.graphs:
            self.graph()(update_actor)
        else:
            self.metrics.update(
                stacked_update(self.state, self.buffer.gather(idx), self.noise, update_actor, **self.args)
            )
