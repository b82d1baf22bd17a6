"""Building MO-Gymnasium environments by id, with checks that they suit MAPEX.

MAPEX needs a continuous Box action space and a vector reward. Termination and truncation
stay separate everywhere: a time-limit cut is not a terminal state.

Nothing here renders, so nothing here chooses an OpenGL backend (MUJOCO_GL): a headless GPU
box without libEGL must be able to train and evaluate. Code that draws frames chooses the
backend where it draws them.
"""

from __future__ import annotations

import importlib
import os
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
    # env.reward_terms (dicts) where the env is a single-objective one made multi-objective
    # (RewardTermsReward); () for an env with a vector reward of its own. Not in spec_meta: DVC
    # tracks the params, and an MO-Gymnasium env's metadata stays what it was.
    reward_terms: tuple = ()


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


def _import_env_module(env_id: str) -> None:
    """Import the module of a `module:EnvId` id (Gymnasium's form: importing the user's package
    registers the env), with the working directory on the import path, as when the user runs
    Python there: a stage runs in the repository root, where the user's own package lives."""
    module = env_id.split(":", 1)[0]
    if not module:
        raise EnvError(f"env.id = {env_id!r}: expected 'module:EnvId' (a module before the colon)")
    cwd = os.getcwd()
    added = cwd not in sys.path
    if added:
        sys.path.insert(0, cwd)
    try:
        importlib.import_module(module)
    except Exception as exc:  # noqa: BLE001 - the user's module: any error is theirs, said in one line
        raise EnvError(f"env.id = {env_id!r}: cannot import module {module!r} ({type(exc).__name__}: {exc})") from None
    finally:
        if added:
            sys.path.remove(cwd)


def make_env(env_id: str, max_episode_steps: int, reward_terms: tuple | list | None = None) -> gym.Env:
    """Build `env_id` with the episode cap `max_episode_steps`; raise EnvError if it doesn't fit.

    `env_id` is an MO-Gymnasium or Gymnasium id, or Gymnasium's `module:EnvId` (the module is
    imported first, which registers the env). `reward_terms` (params env.reward_terms: dicts or
    RewardTerm models) turns a single-objective env into a multi-objective one, one objective per
    term (`RewardTermsReward`); without them the env must return a vector reward itself."""
    import mo_gymnasium  # noqa: F401  (registers the mo-* ids)

    quiet_settotalmass()
    if ":" in env_id:
        _import_env_module(env_id)
    try:
        env = mo_gymnasium.make(env_id, max_episode_steps=max_episode_steps)
    except Exception as exc:  # noqa: BLE001 - unknown id, a constructor that fails: one line either way
        raise EnvError(f"env.id = {env_id!r}: cannot build it ({type(exc).__name__}: {exc})") from None
    if not isinstance(env.action_space, gym.spaces.Box):
        env.close()
        raise EnvError(f"env.id = {env_id!r}: action space is {env.action_space}, expected a continuous Box")
    if len(env.observation_space.shape) != 1:
        env.close()
        raise EnvError(f"env.id = {env_id!r}: observation space {env.observation_space} is not a flat Box")
    if reward_terms:
        if reward_dim(env) is not None:
            env.close()
            raise EnvError(
                f"env.reward_terms: env.id = {env_id!r} already returns a vector reward "
                f"({reward_dim(env)} objectives); leave env.reward_terms null for it"
            )
        env = RewardTermsReward(env, reward_terms)
        _probe_terms(env_id, max_episode_steps, env.terms)
    n = reward_dim(env)
    if n is None or n < 2:
        env.close()
        raise EnvError(
            f"env.id = {env_id!r}: reward is not a vector of >= 2 objectives "
            f"(reward_space = {_reward_space(env)}); expected a multi-objective env, or name the objectives "
            "of a single-objective env in env.reward_terms (one per reward term: a key of the info dict it "
            'returns, or module:function; docs/manual.md, "Your own env")'
        )
    return env


def _probe_terms(env_id: str, max_episode_steps: int, terms: list[dict]) -> None:
    """One step of a separate instance of the env with the middle action, so that a term naming an
    info key the env does not return, or a function that fails, stops here in one line (before any
    training), not in the middle of a run. The env the caller gets is untouched."""
    import mo_gymnasium

    probe = RewardTermsReward(mo_gymnasium.make(env_id, max_episode_steps=max_episode_steps), terms)
    try:
        probe.reset(seed=0)
        space = probe.action_space
        middle = ((np.asarray(space.low, dtype=float) + np.asarray(space.high, dtype=float)) / 2).astype(space.dtype)
        try:
            probe.step(np.nan_to_num(middle))
        except EnvError:
            raise
        except Exception as exc:  # noqa: BLE001 - the user's function or env: one line
            raise EnvError(f"env.reward_terms: a step of {env_id!r} failed ({type(exc).__name__}: {exc})") from None
    finally:
        probe.close()


def _reward_space(env: gym.Env):
    """The env's `reward_space` (MO-Gymnasium's attribute, or a wrapper's), None if it has none."""
    try:
        return env.get_wrapper_attr("reward_space")
    except AttributeError:
        return None


def reward_dim(env: gym.Env) -> int | None:
    """How many objectives the env's reward has (None: a scalar reward, no reward_space)."""
    space = _reward_space(env)
    if space is None or len(getattr(space, "shape", ()) or ()) != 1:
        return None
    return int(space.shape[0])


def _term_value(term: dict, fn, obs, action, reward, next_obs, info) -> float:
    if fn is not None:
        return float(fn(obs, action, reward, next_obs, info))
    return float(info[term["info"]])


class RewardTermsReward(gym.Wrapper):
    """A single-objective env as a multi-objective one: step returns a vector reward, one entry
    per term of env.reward_terms (`scale` times the value of the term's `info` key in the dict
    the env returns that step, or of `function(obs, action, reward, next_obs, info)`, the user's
    own code named module:function), and `reward_space` says its length, as MO-Gymnasium's envs
    do. The env's own scalar reward is dropped (it is what a specialist trained elsewhere saw).

    MO-Gymnasium's wrappers transform vector rewards (LinearReward, MONormalizeReward, ...) but
    none builds one from info keys, hence this wrapper."""

    def __init__(self, env: gym.Env, terms):
        super().__init__(env)
        self.terms = [t.model_dump() if hasattr(t, "model_dump") else dict(t) for t in terms]
        self._fns = [resolve_function(t["function"]) if t.get("function") else None for t in self.terms]
        self.reward_space = gym.spaces.Box(-np.inf, np.inf, shape=(len(self.terms),), dtype=np.float32)
        self._obs = None

    def reset(self, **kwargs):
        obs, info = self.env.reset(**kwargs)
        self._obs = obs
        return obs, info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        values = []
        for term, fn in zip(self.terms, self._fns):
            try:
                value = _term_value(term, fn, self._obs, action, reward, obs, info)
            except KeyError:
                raise EnvError(
                    f"env.reward_terms: info key {term['info']!r} is not in the info dict "
                    f"{self.spec.id if self.spec else 'the env'} returns (keys: {sorted(info)})"
                ) from None
            values.append(float(term.get("scale", 1.0)) * value)
        self._obs = obs
        return obs, np.asarray(values, dtype=np.float64), terminated, truncated, info


def resolve_function(path: str):
    """The callable `module:function` names (the user's own code, imported with the working
    directory on the import path); EnvError in one line if it cannot be found."""
    module, _, name = path.partition(":")
    if not module or not name:
        raise EnvError(f"env.reward_terms: function {path!r}: expected 'module:function'")
    cwd = os.getcwd()
    added = cwd not in sys.path
    if added:
        sys.path.insert(0, cwd)
    try:
        fn = getattr(importlib.import_module(module), name)
    except Exception as exc:  # noqa: BLE001 - the user's module
        raise EnvError(f"env.reward_terms: function {path!r}: cannot load it ({type(exc).__name__}: {exc})") from None
    finally:
        if added:
            sys.path.remove(cwd)
    if not callable(fn):
        raise EnvError(f"env.reward_terms: function {path!r} is not callable")
    return fn


def env_spec(env: gym.Env, env_id: str, max_episode_steps: int) -> EnvSpec:
    """Read the dimensions of an env built by `make_env`."""
    space = env.action_space
    return EnvSpec(
        env_id=env_id,
        obs_dim=int(env.observation_space.shape[0]),
        act_dim=int(space.shape[0]),
        n_objectives=int(reward_dim(env)),
        action_low=tuple(float(x) for x in np.asarray(space.low)),
        action_high=tuple(float(x) for x in np.asarray(space.high)),
        max_episode_steps=max_episode_steps,
        reward_terms=tuple(_terms_of(env)),
    )


def _terms_of(env: gym.Env) -> list[dict]:
    """The reward terms a RewardTermsReward in `env`'s wrapper chain makes its objectives of ([] if none)."""
    while isinstance(env, gym.Wrapper):
        if isinstance(env, RewardTermsReward):
            return [dict(t) for t in env.terms]
        env = env.env
    return []


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
