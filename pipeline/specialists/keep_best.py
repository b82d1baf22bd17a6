"""Keep-best: which of a TD3 specialist's actors its training hands on.

Keep-best (train_specialist.keep_best_every > 0; off by default, as in the paper and plain TD3)
is a hook on the loop that steps a `SpecialistsRun` (`keep_best_hook`, in the hooks of
pipeline.core.drive.drive or run_to_end; the run's `results` refuses to hand on actors when a
due check is missing, so a loop without the hook cannot pass unnoticed): after every env
step t that is a multiple of keep_best_every and past learning_starts, and after the last step
(`keep_best_steps`), each specialist's actor is scored by keep_best_episodes deterministic
episodes (no exploration noise) on an evaluation env of its own, reset with seeds derived from
(seed, objective, check index) alone: the mean undiscounted return on its own objective. A CPU
copy of the best-scoring actor and its target actor (the earlier on ties; never a non-finite
score) is kept, and `SpecialistsRun.results` returns them instead of the final ones; critics and
buffer stay final. The checks draw from no training stream (the training envs, numpy generators,
torch generators and torch's global RNG are untouched), so the training itself is bitwise the
same with keep-best on or off; the snapshots and every check's (step, score) are part of
`SpecialistsRun.state_dict`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import gymnasium as gym
import numpy as np
import torch

from pipeline.core.envs import make_env
from pipeline.core.nets import Actor
from pipeline.core.seeding import derive_seeds
from pipeline.evaluation.episodes import evaluate_policy
from pipeline.params.train_specialist import TrainSpecialistParams
from pipeline.specialists.td3 import unstack_actor


@dataclass
class KeepBest:
    """What keep-best selection (train_specialist.keep_best_every > 0) did for one specialist."""

    every: int  # keep_best_every
    episodes: int  # keep_best_episodes
    checks: list[tuple[int, float]]  # (env step, score) of every check, in order; the last is the final actor's
    step: int | None  # env step of the kept actor; None: no check scored finite, the final actor is kept
    score: float | None  # its score (mean deterministic return on the specialist's own objective)


KEEP_BEST_TAG = 0x6B33_B357  # separates keep-best evaluation seeds from a specialist's training streams


def keep_best_due(cfg: TrainSpecialistParams, learning_starts: int, t: int) -> bool:
    """Whether a keep-best check follows env step t (t steps taken): t a multiple of
    keep_best_every past learning_starts (td3.learning_starts), or the last step; never when
    keep-best is off."""
    every = cfg.keep_best_every
    return every > 0 and learning_starts < t <= cfg.total_steps and (t % every == 0 or t == cfg.total_steps)


def keep_best_steps(cfg: TrainSpecialistParams, learning_starts: int) -> list[int]:
    """Every env step a keep-best check follows, in order ([] when keep-best is off)."""
    return [t for t in range(learning_starts + 1, cfg.total_steps + 1) if keep_best_due(cfg, learning_starts, t)]


def keep_best_seeds(seed: int, objective: int, check: int, episodes: int) -> list[int]:
    """Env reset seeds of keep-best check number `check` (0-based) of specialist (seed, objective)."""
    return derive_seeds(seed, objective, KEEP_BEST_TAG, check, n=episodes)


def keep_best_score(actor: Actor, env: gym.Env, objective: int, seeds: Sequence[int]) -> float:
    """Mean undiscounted return on `objective` of deterministic episodes of `actor` (CPU), one
    per seed, one after another on `env`. NaN, without running any episode, if a weight is not
    finite (MuJoCo would be stepped with NaN actions)."""
    if not all(bool(torch.isfinite(v).all()) for v in actor.state_dict().values()):
        return math.nan
    returns = [evaluate_policy(actor, [env], [int(s)]).returns[0, objective] for s in seeds]
    return float(np.mean(returns))


def keep_best_hook(run) -> None:
    """After a step of `run` (a pipeline.specialists.td3_training.SpecialistsRun): where a check
    is due (`keep_best_due`), score every specialist's current actor (`keep_best_score`, on an
    evaluation env of its own, seeds from (seed, objective, check index)); record (step, score)
    in `run.checks` and keep a CPU copy of the actor and its target actor in `run.best` if the
    score is finite and beats the best so far. Nothing else of the run is touched."""
    if not keep_best_due(run.cfg, run.td3.learning_starts, run.t):
        return
    if run.eval_envs is None:
        run.eval_envs = [make_env(run.spec.env_id, run.spec.max_episode_steps, run.spec.reward_terms) for _ in run.jobs]
    for s, ((seed, objective), env) in enumerate(zip(run.jobs, run.eval_envs)):
        seeds = keep_best_seeds(seed, objective, len(run.checks[s]), run.cfg.keep_best_episodes)
        actor = unstack_actor(run.state.actor, s)
        score = keep_best_score(actor, env, objective, seeds)
        run.checks[s].append((run.t, score))
        best = run.best[s]
        if math.isfinite(score) and (best is None or score > best["score"]):
            run.best[s] = {
                "step": run.t,
                "score": score,
                "actor": actor.state_dict(),
                "actor_target": unstack_actor(run.state.actor_target, s).state_dict(),
            }
