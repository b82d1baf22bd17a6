"""Mid-episode env-state snapshots: the whole state of a MuJoCo env behind gymnasium's standard
wrappers (physics, the derived quantities env code reads, the wrappers' counters, the RNG
states) saved as CPU tensors and restored bitwise, and `env_checkpoint_problem`, which says why
another env cannot be checkpointed. Used by `SpecialistsRun.state_dict`
(pipeline/specialists/td3_training.py) and the train_specialist stage."""

from __future__ import annotations

import copy
from typing import Any

import gymnasium as gym
import numpy as np
import torch


class EnvStateError(ValueError):
    """An env whose whole state cannot be saved and restored (so it cannot be checkpointed)."""


# Wrappers the env state knows: TimeLimit (its step count is saved), OrderEnforcing (its
# has-reset flag is saved) and PassiveEnvChecker (its flags only decide which one-off checks
# run; they change nothing the env returns). Any other wrapper may hold state we cannot see.
_KNOWN_WRAPPERS = (gym.wrappers.TimeLimit, gym.wrappers.OrderEnforcing, gym.wrappers.PassiveEnvChecker)

# Quantities MuJoCo derives from the state during a step (positions, frames, velocities and
# forces of bodies, geoms and sites). mj_step recomputes all of them before it uses them, so
# they are not part of the integration state, but env code may read them before stepping:
# Ant-v5 takes the torso's xpos before the step to compute its velocity, and after a step
# xpos still belongs to the last substep's start, not to the current qpos. So they are saved
# as they are, not recomputed on restore.
_MJ_DERIVED = (
    "xpos",
    "xquat",
    "xmat",
    "xipos",
    "ximat",
    "xanchor",
    "xaxis",
    "geom_xpos",
    "geom_xmat",
    "site_xpos",
    "site_xmat",
    "subtree_com",
    "cinert",
    "cdof",
    "cvel",
    "cacc",
    "cfrc_int",
    "cfrc_ext",
    "qacc",
    "qfrc_actuator",
    "actuator_force",
    "sensordata",
)


def _wrapper_chain(env: gym.Env) -> list[gym.Env]:
    chain = []
    while isinstance(env, gym.Wrapper):
        chain.append(env)
        env = env.env
    return chain


def env_checkpoint_problem(env: gym.Env) -> str | None:
    """Why the mid-episode state of `env` cannot be saved, or None if `env_state` can save it."""
    unknown = [type(w).__name__ for w in _wrapper_chain(env) if not isinstance(w, _KNOWN_WRAPPERS)]
    if unknown:
        return f"wrapper(s) {unknown} may hold state the checkpoint cannot see"
    u = env.unwrapped
    try:
        import mujoco
    except ImportError:  # pragma: no cover - mujoco comes with the MuJoCo envs
        return "mujoco is not installed"
    if not isinstance(getattr(u, "model", None), mujoco.MjModel) or not isinstance(
        getattr(u, "data", None), mujoco.MjData
    ):
        return f"{type(u).__name__} is not a MuJoCo env (only MuJoCo physics state is saved)"
    return None


def env_state(env: gym.Env) -> dict[str, Any]:
    """The whole mid-episode state of a MuJoCo env built by `make_env`: the physics
    (mjSTATE_INTEGRATION: time, qpos, qvel, act, warm start of the constraint solver, controls,
    ...), the derived quantities env code may read before the next step (`_MJ_DERIVED`), the
    wrappers' counters and the env's and its action space's RNG states.

    qpos and qvel alone are not enough: without the solver's warm start a step with contacts
    (Hopper, Walker2d, Ant) differs in the last bits. Raises EnvStateError if the env is not
    one whose state this knows (see `env_checkpoint_problem`)."""
    problem = env_checkpoint_problem(env)
    if problem is not None:
        raise EnvStateError(problem)
    import mujoco

    u = env.unwrapped
    sig = mujoco.mjtState.mjSTATE_INTEGRATION
    physics = np.empty(mujoco.mj_stateSize(u.model, sig), np.float64)
    mujoco.mj_getState(u.model, u.data, physics, sig)
    wrappers = []
    for w in _wrapper_chain(env):
        entry: dict[str, Any] = {"type": type(w).__name__}
        if isinstance(w, gym.wrappers.TimeLimit):
            entry["elapsed_steps"] = w._elapsed_steps
        if isinstance(w, gym.wrappers.OrderEnforcing):
            entry["has_reset"] = w._has_reset
        wrappers.append(entry)
    return {
        "physics": torch.from_numpy(physics),
        "derived": {k: torch.from_numpy(np.array(getattr(u.data, k))) for k in _MJ_DERIVED if hasattr(u.data, k)},
        "wrappers": wrappers,
        "np_random": copy.deepcopy(u.np_random.bit_generator.state),
        "action_space": copy.deepcopy(env.action_space.np_random.bit_generator.state),
    }


def restore_env_state(env: gym.Env, state: dict[str, Any]) -> None:
    """Put `env` (built like the one `state` was taken from) into `state` (an `env_state`):
    its next steps and resets give exactly what the saved env's would have. ValueError if the
    state does not fit the env."""
    problem = env_checkpoint_problem(env)
    if problem is not None:
        raise EnvStateError(problem)
    import mujoco

    u = env.unwrapped
    sig = mujoco.mjtState.mjSTATE_INTEGRATION
    physics = state["physics"].numpy()
    if physics.shape != (mujoco.mj_stateSize(u.model, sig),):
        raise ValueError(f"physics state of shape {tuple(physics.shape)} does not fit this env's model")
    chain = _wrapper_chain(env)
    if [type(w).__name__ for w in chain] != [w["type"] for w in state["wrappers"]]:
        raise ValueError(
            f"env wrappers {[w['type'] for w in state['wrappers']]} were saved, this env has {[type(w).__name__ for w in chain]}"
        )
    mujoco.mj_setState(u.model, u.data, physics, sig)
    mujoco.mj_forward(u.model, u.data)  # derived quantities not saved: consistent with the state
    for k, v in state["derived"].items():
        target = getattr(u.data, k, None)
        if target is None:
            raise ValueError(f"saved mjData.{k}, which this MuJoCo version lacks")
        if target.shape != tuple(v.shape):
            raise ValueError(f"saved mjData.{k} has shape {tuple(v.shape)}, this env's {target.shape}")
        target[...] = v.numpy()
    mujoco.mj_setState(u.model, u.data, physics, sig)  # in case mj_forward touched any of it
    for w, saved in zip(chain, state["wrappers"]):
        if "elapsed_steps" in saved:
            w._elapsed_steps = saved["elapsed_steps"]
        if "has_reset" in saved:
            w._has_reset = saved["has_reset"]
    u.np_random.bit_generator.state = state["np_random"]
    env.action_space.np_random.bit_generator.state = state["action_space"]
