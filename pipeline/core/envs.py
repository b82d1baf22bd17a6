"""Building MO-Gymnasium environments by id, with checks that they suit MAPEX.

MAPEX needs a continuous Box action space and a vector reward. Termination and truncation
stay separate everywhere: a time-limit cut is not a terminal state.

Nothing here renders, so nothing here chooses an OpenGL backend (MUJOCO_GL): a headless GPU
box without libEGL must be able to train and evaluate. Code that draws frames chooses the
backend where it draws them.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

import gymnasium as gym
import numpy as np

from pipeline.params.env_facts import objective_names_of


class EnvError(ValueError):
    """The env id is unknown or the env does not fit MAPEX (discrete actions, scalar reward)."""


@dataclass(frozen=True)
class EnvSpec:
    """Dimensions and bounds of an env, as recorded in every artifact's metadata."""

    env_id: str
    obs_dim: int
    act_dim: int
    n_objectives: int
    action_low: tuple[float, ...]
    action_high: tuple[float, ...]
    max_episode_steps: int


def spec_meta(spec: EnvSpec) -> dict:
    """The env part of an artifact's metadata: env_id, dims and action bounds (JSON-able)."""
    return {
        "env_id": spec.env_id,
        "obs_dim": spec.obs_dim,
        "act_dim": spec.act_dim,
        "n_objectives": spec.n_objectives,
        "action_low": list(spec.action_low),
        "action_high": list(spec.action_high),
    }


# MuJoCo 4.0.1 warns that the `settotalmass` compiler attribute of Gymnasium's model files
# (HalfCheetah, Hopper, ...) is deprecated, from C, on stderr, each time a model is compiled: four
# times per process in every stage's output, about a file the user cannot change. This one
# message is dropped; every other MuJoCo warning is printed as MuJoCo prints it.
DEPRECATED_TOTALMASS = "compiler attribute 'settotalmass' is deprecated"


def _mujoco_warning(message: str) -> None:
    if not message.startswith(DEPRECATED_TOTALMASS):
        sys.stderr.write(f"WARNING: {message}\n\n")
        sys.stderr.flush()


def quiet_settotalmass() -> None:
    """Install `_mujoco_warning` as MuJoCo's warning handler (where none other is installed)."""
    try:
        import mujoco
    except ImportError:  # an env without MuJoCo: nothing prints the message
        return
    if mujoco.get_mju_user_warning() is None:
        mujoco.set_mju_user_warning(_mujoco_warning)


def make_env(env_id: str, max_episode_steps: int) -> gym.Env:
    """Build `env_id` with the episode cap `max_episode_steps`; raise EnvError if it doesn't fit."""
    import mo_gymnasium  # noqa: F401  (registers the mo-* ids)

    quiet_settotalmass()

    try:
        env = mo_gymnasium.make(env_id, max_episode_steps=max_episode_steps)
    except gym.error.Error as exc:
        raise EnvError(f"env.id = {env_id!r}: cannot build it ({exc})") from None
    if not isinstance(env.action_space, gym.spaces.Box):
        env.close()
        raise EnvError(f"env.id = {env_id!r}: action space is {env.action_space}, expected a continuous Box")
    reward_space = getattr(env.unwrapped, "reward_space", None)
    if reward_space is None or len(reward_space.shape) != 1 or reward_space.shape[0] < 2:
        env.close()
        raise EnvError(
            f"env.id = {env_id!r}: reward is not a vector of >= 2 objectives "
            f"(reward_space = {reward_space}); expected a multi-objective env"
        )
    if len(env.observation_space.shape) != 1:
        env.close()
        raise EnvError(f"env.id = {env_id!r}: observation space {env.observation_space} is not a flat Box")
    return env


def env_spec(env: gym.Env, env_id: str, max_episode_steps: int) -> EnvSpec:
    """Read the dimensions of an env built by `make_env`."""
    space = env.action_space
    return EnvSpec(
        env_id=env_id,
        obs_dim=int(env.observation_space.shape[0]),
        act_dim=int(space.shape[0]),
        n_objectives=int(env.unwrapped.reward_space.shape[0]),
        action_low=tuple(float(x) for x in np.asarray(space.low)),
        action_high=tuple(float(x) for x in np.asarray(space.high)),
        max_episode_steps=max_episode_steps,
    )


def objective_names(env_id: str, n_objectives: int, override: list[str] | None = None) -> list[str]:
    """Human-readable objective names: the params override, the env's entry in presets/envs.yaml
    (`objective_names`), or 'objective m'."""
    if override is not None:
        if len(override) != n_objectives:
            raise EnvError(f"env.objective_names has {len(override)} names, env {env_id} has {n_objectives} objectives")
        return list(override)
    names = objective_names_of(env_id)
    if names is not None and len(names) == n_objectives:
        return list(names)
    return [f"objective {m}" for m in range(n_objectives)]
