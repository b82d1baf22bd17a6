"""Checks of the env params that fail a run before its work, not after it.

Everything a later stage would refuse for an env is checked where the run is planned (`mapex
plan`, which `make repro` runs first) and, but for the reference point, by the stages that
start a run (the specialists' training, an import, MORL/D): the id builds (an MO-Gymnasium or
Gymnasium id, or `module:EnvId`), its actions are a continuous Box, its reward is a vector or
env.reward_terms names its objectives (each term probed with one step: a key the info dict lacks
fails here), objective_names has one name per objective, and stage score will know a reference
point (env.reference_point, or the env's entry in presets/envs.yaml). Each problem is one line
naming the key and what was expected (EnvError or ParamsError, which every stage prints as one).
"""

from __future__ import annotations

from pathlib import Path

from pipeline.core.envs import EnvError, EnvSpec, env_spec, make_env, objective_names
from pipeline.evaluation.reference_points import TABLE, resolve_reference_point
from pipeline.params import ParamsError


def preflight(env_p, params: Path, reference: bool = True, table: Path = TABLE) -> EnvSpec:
    """The env of `env_p` (params section env of file `params`) built and checked as above; its
    spec. `reference`: check the reference point too (planning does; the training stages, which
    do not read it, leave it to planning and to stage score)."""
    env = make_env(env_p.id, env_p.max_episode_steps, env_p.reward_terms)
    try:
        spec = env_spec(env, env_p.id, env_p.max_episode_steps)
    finally:
        env.close()
    try:
        objective_names(env_p.id, spec.n_objectives, env_p.objective_names)
    except EnvError as exc:
        raise EnvError(f"{params}: {exc}") from None
    if reference:
        resolve_reference_point(env_p.reference_point, env_p.id, spec.n_objectives, params, table)
    return spec


def specialists_to_train(
    env_p, params: Path, chosen: list[int] | None, listed: list[int]
) -> tuple[EnvSpec, list[int], list[str]]:
    """The preamble of the stages that train specialists (train_specialist, train_pderl): the env
    checked (`preflight`, no reference point), the objectives to train (`chosen`, the stage's
    --objective options, else `listed`, params' objectives), each checked against the env's
    (one line naming the option or the key), and every objective's name. Returns (spec,
    objectives, names)."""
    objectives = list(chosen) if chosen else list(listed)
    spec = preflight(env_p, params, reference=False)  # the env builds and fits, in one line if not
    bad = [k for k in objectives if not 0 <= k < spec.n_objectives]
    if bad:
        where = f"--objective {bad[0]}" if chosen else f"{params}: objectives = {objectives}"
        raise ParamsError(f"{where}: env {env_p.id} has objectives 0..{spec.n_objectives - 1}")
    return spec, objectives, objective_names(env_p.id, spec.n_objectives, env_p.objective_names)
