"""Collecting a replay buffer for a specialist trained elsewhere: roll its policy out in the MO env.

An imported specialist comes without a buffer MAPEX can use: an SB3 buffer holds only the scalar
reward it was trained on, and CleanRL and TorchScript give none. MAPEX's hybrid buffer and
every critic Q^(k)_m need transitions of pi_k's own state distribution with the full reward
vector, so `CollectionRun` rolls pi_k out with Gaussian exploration noise, as TD3 explores
(std `noise` times the action half-range, clipped to the bounds), episodes capped at
env.max_episode_steps, termination and truncation kept apart. The rows are written in the
project's buffer format (pipeline.core.buffer). These env frames are this path's sample cost.

Deviation from the paper: its buffers are the specialists' own training buffers (the latest
transitions of training). A collected buffer is on-policy for the final pi_k plus noise
instead, narrower than a training buffer; documented in docs/import_export.md.

Like every long run it is a pipeline.core.drive.Run, with `state_dict`/`load_state_dict` (rows
so far, the env's mid-episode state, RNG states), so a killed collection resumes to the same rows.
"""

from __future__ import annotations

import copy
from typing import Any, Callable

import gymnasium as gym
import numpy as np
import torch

from pipeline.core.artifacts import ArtifactError
from pipeline.core.buffer import ReplayBuffer
from pipeline.core.drive import fmt_vec
from pipeline.core.envs import EnvSpec
from pipeline.core.envstate import env_state, restore_env_state
from pipeline.core.seeding import derive_seeds

STATE_FORMAT = "mapex.collection_state"
STATE_VERSION = 1
COLLECT_STREAM = 0xC011  # seed key: collection draws apart from training's and extraction's


class CollectionRun:
    """`rows` transitions of `actor` (objective k's imported policy) in `env`, one `step` at a time."""

    def __init__(
        self,
        actor,
        env: gym.Env,
        spec: EnvSpec,
        rows: int,
        noise: float,
        seed: int,
        objective: int,
        checkpoint_every: int = 0,
        source: str = "the imported policy",
    ):
        """checkpoint_every: rows between two periodic checkpoints (0: none; `checkpoint_due`);
        source: the policy's file, named when the policy returns a non-finite action."""
        self.actor, self.env, self.spec, self.source = actor.eval(), env, spec, source
        self.rows, self.noise = int(rows), float(noise)
        s_np, s_env, s_space = derive_seeds(seed, objective, COLLECT_STREAM, n=3)
        self.rng = np.random.default_rng(s_np)
        env.action_space.seed(s_space)
        self.low = np.asarray(spec.action_low, np.float32)
        self.high = np.asarray(spec.action_high, np.float32)
        self.buffer = ReplayBuffer(max(self.rows, 1), spec.obs_dim, spec.act_dim, spec.n_objectives)
        self.obs = np.asarray(env.reset(seed=s_env)[0], np.float32)
        self.episode = 0
        self.ep_step = 0
        self.ep_return = np.zeros(spec.n_objectives)
        self.returns: list[list[float]] = []  # per finished episode: its undiscounted return vector
        self.t = 0
        self.checkpoint_every = int(checkpoint_every)
        self.ended: list[float] | None = None  # the return vector of the episode the last step ended
        self.on_progress: Callable[[], None] | None = None  # pipeline.core.drive.Run (a step is short: unused)

    @property
    def done(self) -> bool:
        return self.t >= self.rows

    # -- the verbs of pipeline.core.drive.Run ---------------------------------------------

    def start(self) -> None:
        """Nothing before the first row (the env was reset when the run was made)."""

    def finish(self) -> None:
        """Nothing follows the last row: the rows are the output (`data`)."""

    def progress(self) -> tuple[int, str]:
        """Rows collected; the return of the episode the last row ended ("" if it ended none)."""
        return self.t, "" if self.ended is None else f"return {fmt_vec(self.ended)}"

    def checkpoint_due(self) -> bool:
        """Every checkpoint_every rows but the last (none when it is 0)."""
        every = self.checkpoint_every
        return bool(every) and self.t > 0 and self.t % every == 0 and not self.done

    def where(self) -> str:
        return f"row {self.t}"

    def close(self) -> None:
        self.env.close()

    def action(self) -> np.ndarray:
        """The policy's action for the current observation, plus exploration noise, clipped to the
        bounds; ArtifactError naming the file and the row if the policy's action is not finite
        (clipping would keep a NaN, and the env would be stepped with it)."""
        with torch.no_grad():
            a = self.actor(torch.as_tensor(self.obs, dtype=torch.float32)[None])[0].numpy().astype(np.float32)
        if not np.isfinite(a).all():
            bad = ", ".join(f"{x:g}" for x in a[~np.isfinite(a)][:3])
            raise ArtifactError(
                f"{self.source}: the policy returned a non-finite action ({bad}) at row {self.t} "
                f"(episode {self.episode}, step {self.ep_step}); collection stopped, no buffer written"
            )
        if self.noise > 0:
            half = (self.high - self.low) / 2
            a = a + self.rng.normal(0.0, self.noise, size=a.shape).astype(np.float32) * half
        return np.clip(a, self.low, self.high).astype(np.float32)

    def step(self) -> list[float] | None:
        """One env step; returns the return vector of the episode it ended, else None."""
        self.ended = self._step()
        return self.ended

    def _step(self) -> list[float] | None:
        a = self.action()
        next_obs, reward, terminated, truncated, _ = self.env.step(a)
        reward = np.asarray(reward, np.float32)
        self.buffer.add(self.obs, a, reward, next_obs, bool(terminated), bool(truncated), self.episode, self.ep_step)
        self.ep_return += reward
        self.ep_step += 1
        self.t += 1
        self.obs = np.asarray(next_obs, np.float32)
        if terminated or truncated:
            ended = self.ep_return.tolist()
            self.returns.append(ended)
            self.obs = np.asarray(self.env.reset()[0], np.float32)
            self.episode += 1
            self.ep_step = 0
            self.ep_return = np.zeros(self.spec.n_objectives)
            return ended
        return None

    def data(self) -> dict[str, np.ndarray]:
        """The rows collected, in order (pipeline.core.buffer's fields)."""
        return self.buffer.chronological()

    def state_dict(self) -> dict[str, Any]:
        n = self.buffer.size
        return {
            "format": STATE_FORMAT,
            "format_version": STATE_VERSION,
            "t": self.t,
            "rows": {k: torch.from_numpy(v[:n].copy()) for k, v in self.buffer.data.items()},
            "loop": {
                "obs": torch.from_numpy(self.obs.copy()),
                "episode": self.episode,
                "ep_step": self.ep_step,
                "ep_return": torch.from_numpy(self.ep_return.copy()),
            },
            "returns": torch.tensor(self.returns, dtype=torch.float64).reshape(-1, self.spec.n_objectives),
            "rng": copy.deepcopy(self.rng.bit_generator.state),
            "env": env_state(self.env),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a `state_dict` of a collection with the same policy, env, rows, noise and seed
        (on a fresh run); raises ValueError if it cannot be one."""
        if state.get("format") != STATE_FORMAT or state.get("format_version") != STATE_VERSION:
            raise ValueError(f"not a {STATE_FORMAT} v{STATE_VERSION} state")
        if self.t:
            raise ValueError("load_state_dict needs a fresh run")
        t = int(state["t"])
        if not 0 <= t <= self.rows or any(len(v) != t for v in state["rows"].values()):
            raise ValueError(f"state of {t} rows does not fit a collection of {self.rows}")
        try:
            for k, v in state["rows"].items():
                self.buffer.data[k][:t] = v.numpy()
            self.buffer.ptr, self.buffer.size = t % self.buffer.capacity, t
            restore_env_state(self.env, state["env"])
            loop = state["loop"]
            self.obs = loop["obs"].numpy().astype(np.float32, copy=True)
            self.episode, self.ep_step = int(loop["episode"]), int(loop["ep_step"])
            self.ep_return = loop["ep_return"].numpy().astype(np.float64, copy=True)
            self.returns = state["returns"].tolist()
            self.rng.bit_generator.state = state["rng"]
        except (KeyError, RuntimeError, TypeError) as exc:
            raise ValueError(f"state does not fit this collection ({type(exc).__name__}: {exc})") from None
        self.t = t
