"""Networks: the deterministic actor and the batched critic ensemble.

The critic ensemble holds every critic of a specialist (twin heads for each objective it
covers) as stacked weight tensors, so all of them are evaluated by a few batched matmuls
and trained by one optimizer rather than by N modules in a Python loop.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
from torch import nn


def mlp(in_dim: int, hidden_sizes: Sequence[int], out_dim: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    d = in_dim
    for h in hidden_sizes:
        layers += [nn.Linear(d, h), nn.ReLU()]
        d = h
    layers.append(nn.Linear(d, out_dim))
    return nn.Sequential(*layers)


class Actor(nn.Module):
    """Deterministic policy: obs (B, obs_dim) -> action (B, act_dim) inside [low, high]."""

    def __init__(self, obs_dim: int, act_dim: int, hidden_sizes: Sequence[int], low, high):
        super().__init__()
        self.net = mlp(obs_dim, hidden_sizes, act_dim)
        low_t = torch.as_tensor(low, dtype=torch.float32)
        high_t = torch.as_tensor(high, dtype=torch.float32)
        # Saved in the state dict so a checkpoint carries its own bounds.
        self.register_buffer("scale", (high_t - low_t) / 2)
        self.register_buffer("centre", (high_t + low_t) / 2)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.centre + self.scale * torch.tanh(self.net(obs))


class CriticEnsemble(nn.Module):
    """`n_members` independent Q-networks Q_e(s, a), e = 0..n_members-1, as stacked weights.

    Member layout used throughout MAPEX: member 2*j + h is head h (0 or 1) of the j-th
    objective the ensemble covers. Layer l has weight (E, d_in, d_out) and bias (E, 1, d_out),
    initialised like `nn.Linear` (uniform in +-1/sqrt(d_in)).
    """

    def __init__(self, obs_dim: int, act_dim: int, hidden_sizes: Sequence[int], n_members: int):
        super().__init__()
        self.n_members = n_members
        dims = [obs_dim + act_dim, *hidden_sizes, 1]
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for d_in, d_out in zip(dims[:-1], dims[1:]):
            bound = 1.0 / math.sqrt(d_in)
            self.weights.append(nn.Parameter(torch.empty(n_members, d_in, d_out).uniform_(-bound, bound)))
            self.biases.append(nn.Parameter(torch.empty(n_members, 1, d_out).uniform_(-bound, bound)))

    def forward(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Q of every member at the same (obs (B, o), action (B, a)) -> (E, B)."""
        x = torch.cat([obs, action], dim=-1)
        # (B, d) @ (E, d, h) broadcasts to (E, B, h): one batched matmul for every member.
        # ReLU in place saves an allocation per layer; the matmuls that produce h do not keep
        # it for their backward, so autograd allows it.
        h = torch.relu_(torch.matmul(x, self.weights[0]) + self.biases[0])
        n = len(self.weights)
        for i in range(1, n):
            h = torch.baddbmm(self.biases[i], h, self.weights[i])
            if i < n - 1:
                h = torch.relu_(h)
        return h.squeeze(-1)

    def member(self, obs: torch.Tensor, action: torch.Tensor, e: int) -> torch.Tensor:
        """Q of member `e` alone at (obs (B, o), action (B, a)) -> (B,)."""
        h = torch.cat([obs, action], dim=-1)
        n = len(self.weights)
        for i in range(n):
            h = torch.addmm(self.biases[i][e], h, self.weights[i][e])
            if i < n - 1:
                h = torch.relu_(h)
        return h.squeeze(-1)

    def twin_min(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Clipped double-Q estimate per covered objective: min over the two heads -> (n_obj, B)."""
        q = self.forward(obs, action)
        return q.view(self.n_members // 2, 2, -1).min(dim=1).values
