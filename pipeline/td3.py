"""TD3 updates for a specialist and its secondary critics, as small composable pieces.

Specialist k's actor ascends only its primary critic Q^(k)_k (head 0, as in TD3). Every
critic in the ensemble (primary and secondary) regresses onto the same TD3 target rule:
y_m = r_m + gamma * (1 - terminated) * min_h Q'_{m,h}(s', clip(pi'(s') + clip(noise))),
computed with the specialist's own target policy (paper, section "Secondary Critics").
A truncated (time-limit) transition is not terminal, so the target bootstraps through it.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from pipeline.buffer import Batch
from pipeline.nets import Actor, CriticEnsemble


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
