"""TD3Learner: one TD3 agent with secondary critics that learns from transitions handed to it,
the RL agent inside PDERL and MOPDERL. It is the stacked specialists' machinery of
pipeline/specialists/td3_training.py with S = 1 (its updater, pipeline/specialists/td3.py, and its state
save/restore helpers, pipeline/specialists/td3_state.py), so it gets the same CPU and CUDA paths."""

from __future__ import annotations

import copy
from typing import Any

import numpy as np
import torch

from pipeline.core.buffer import StackedReplay
from pipeline.core.envs import EnvSpec
from pipeline.core.finite import check_finite, due
from pipeline.core.nets import Actor, CriticEnsemble
from pipeline.params.td3 import TD3Params
from pipeline.specialists.td3 import StackedTD3, Updater
from pipeline.specialists.td3_state import (
    buffer_state,
    check_buffer_state,
    finite_named,
    load_buffer_state,
    load_nets_state,
    nets_state,
)


class TD3Learner:
    """One TD3 agent with secondary critics that learns from transitions handed to it: the RL
    agent inside PDERL and MOPDERL, whose episodes are run by the population's loop.

    It is the specialists' machinery with S = 1 (a stacked network set, a `StackedReplay` on
    the training device and `Updater`), so it gets the same device path: on CUDA the buffer
    lives on the GPU, minibatch rows are drawn there from `cuda_rows_seed`, and with
    cfg.cuda_graphs each update replays two captured CUDA graphs; `train(n)` makes n updates
    with no host sync but the finiteness check every CHECK_EVERY updates. On a CPU, rows are drawn with `rows_rng` (numpy).
    `precision` ("fp32" or "bf16", resolved: pipeline.core.precision) is its updates' arithmetic.
    """

    def __init__(
        self,
        spec: EnvSpec,
        cfg: TD3Params,
        state: StackedTD3,
        rows_rng: np.random.Generator,
        noise_seed: int,
        cuda_rows_seed: int,
        device: torch.device | str,
        precision: str = "fp32",
    ):
        if state.n != 1:
            raise ValueError(f"a TD3Learner trains one specialist, got a stacked set of {state.n}")
        self.cfg, self.state, self.device = cfg, state, torch.device(device)
        self.rows_rng = rows_rng
        self.buffer = StackedReplay(1, cfg.buffer_size, spec.obs_dim, spec.act_dim, spec.n_objectives, self.device)
        self.update = Updater(
            state,
            self.buffer,
            cfg,
            [{"noise": noise_seed, "cuda_rows": cuda_rows_seed}],
            [rows_rng],
            self.device,
            precision,
        )
        self.objectives: list[int] = state.reward_index[0].tolist()
        self.primary_member = int(state.primary_members[0])  # head 0 of its own objective
        self.updates = 0

    def add(self, obs, action, reward, next_obs, terminated: bool, truncated: bool, episode: int, step: int) -> None:
        """Append one transition to the replay buffer."""
        self.buffer.add(
            obs[None],
            action[None],
            np.asarray(reward)[None],
            next_obs[None],
            np.array([terminated]),
            np.array([truncated]),
            np.array([episode]),
            np.array([step]),
        )

    def train(self, n: int) -> None:
        """n TD3 updates (the actor and targets on every policy_freq-th, counted over the run).
        Raises TrainingDiverged (unit "update") if a check every CHECK_EVERY updates finds a
        loss or weight that is not finite (pipeline.core.finite)."""
        for _ in range(n):
            self.updates += 1
            self.update(update_actor=self.updates % self.cfg.policy_freq == 0)
            if due(self.updates):
                self.check_finite()

    def check_finite(self, full: bool = False) -> None:
        """Raise TrainingDiverged if the latest losses or a weight is not finite; with `full`
        also the targets, the optimizer moments and the replay buffer (td3_state.finite_named).
        The run that owns the learner adds its seed and objective."""
        check_finite(finite_named(self.update, full), self.updates, unit="update")

    def actor(self) -> Actor:
        """A copy of the current actor, on the training device (to act with or copy from)."""
        with torch.random.fork_rng(devices=[]):  # building an Actor draws an init we overwrite
            return self.state.actor.unstack(0).to(self.device)

    def q_primary(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The primary critic's head 0 (Q1, the head the actor ascends) at (obs (B, o), action (B, a)) -> (B,)."""
        return self.state.critic.member(obs, action, self.primary_member)

    def networks(self) -> tuple[Actor, Actor, CriticEnsemble, CriticEnsemble]:
        """CPU copies of (actor, actor_target, critic, critic_target): the artifact formats."""
        st = self.state
        e = st.critic.n_members
        with torch.random.fork_rng(devices=[]):
            return (
                st.actor.unstack(0),
                st.actor_target.unstack(0).requires_grad_(False),
                st.critic.subset(0, e).cpu(),
                st.critic_target.subset(0, e).cpu().requires_grad_(False),
            )

    def state_dict(self) -> dict[str, Any]:
        """Networks, optimizers, buffer, RNG streams and the update count, as CPU tensors."""
        u = self.update
        return {
            "updates": self.updates,
            "nets": nets_state(self.state),
            "buffer": buffer_state(self.buffer),
            "rng": {
                "rows": copy.deepcopy(self.rows_rng.bit_generator.state),
                "noise": u.noise_gens[0].get_state(),
                "cuda_rows": u.row_gens[0].get_state() if u.on_cuda else None,
            },
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a `state_dict` into a fresh learner (ValueError if it does not fit)."""
        if self.updates:
            raise ValueError("load_state_dict needs a fresh learner")
        check_buffer_state(self.buffer, state["buffer"])
        load_buffer_state(self.buffer, state["buffer"])
        load_nets_state(self.update, state["nets"], state["updates"])
        rng = state["rng"]
        self.rows_rng.bit_generator.state = rng["rows"]
        self.update.noise_gens[0].set_state(rng["noise"])
        if self.update.on_cuda and rng["cuda_rows"] is not None:
            self.update.row_gens[0].set_state(rng["cuda_rows"])
        self.updates = int(state["updates"])
