"""The weight-space interpolation baseline: policies mixed from the specialists' weights.

A baseline the paper does not have. Between specialists A and B with actors of one
architecture, the policy of mixing weight l has the parameters theta = (1 - l) theta_A + l theta_B
("rewarded soups", Rame et al. 2023); with N >= 3 specialists, theta = sum_i w_i theta_i for a
weight vector w on the simplex. It costs no training, only the evaluations of its policies, and
is the first thing a front made from specialists should beat. Mixing independently initialised
networks is expected to fail in the middle of the grid (the literature wants a shared
initialisation: `td3.shared_init`); a quick probe on the quickstart's TD3 specialists found a
rough front anyway (issue 31).

The grid: the points w = k / H of the simplex lattice of resolution H (k non-negative integers
summing to H) other than its N vertices, with H the finest resolution whose non-vertex points
number at most `policies` (the children of the MAPEX run it is compared with). For N = 2 that
is exactly `policies` points, l = 1/H, ..., (H - 1)/H with H = policies + 1; for N >= 3 it can be
fewer (12 children of 3 objectives: H = 4, 12 points; 48: H = 8, 42 points). The vertices
(l = 0 and l = 1) are the specialists themselves: they are in the population already, as its
starting policies, as in every method's population, so the grid leaves them out rather than
evaluate a copy of each.
"""

from __future__ import annotations

from typing import Callable, Sequence

import gymnasium as gym
import torch

# The grid and the mix live in pipeline.core.mixing (extraction's hybrid start reuses them);
# imported here under their old names, which the stage and the tests use.
from pipeline.core.cost import Stopwatch, cost_row
from pipeline.core.mixing import architecture_problem as architecture_problem
from pipeline.core.mixing import chosen_specialists as chosen_specialists
from pipeline.core.mixing import grid_resolution as grid_resolution
from pipeline.core.mixing import mix_actors as mix_actors
from pipeline.core.mixing import mixing_weights as mixing_weights
from pipeline.core.mixing import non_vertex_count as non_vertex_count
from pipeline.core.mixing import simplex_points as simplex_points
from pipeline.core.mixing import starts_problem as starts_problem
from pipeline.core.nets import Actor
from pipeline.core.population import Member, actor_state
from pipeline.core.specialist import StartingPolicy
from pipeline.evaluation.episodes import EvalResult, eval_seeds, evaluate_policy

# Extraction's evaluation stream (pipeline.extraction.run.EVAL_STREAM; a test checks they agree),
# so member i is evaluated on the episodes MAPEX's member i is: the starting policies get the
# returns MAPEX's population starts with, and interpolated policy j those of MAPEX's child j.
EVAL_STREAM = 0
ORIGIN = "interpolated"  # the members' origin in population.pt (the starting policies': "specialist")


def interpolate(
    starts: Sequence[StartingPolicy],
    n_objectives: int,
    policies: int,
    per_iteration: int,
    eval_episodes: int,
    seed: int,
    envs: Sequence[gym.Env],
    on_member: Callable[[Member], None] | None = None,
    costs: list[dict] | None = None,
    make_mixer: Callable[[Sequence[Actor]], Callable[[Sequence[float]], Actor]] | None = None,
) -> list[Member]:
    """The interpolation baseline's population: every starting policy evaluated (members
    0 .. n_start - 1, as extraction's population starts), then one member per point of the grid
    (`mixing_weights(n_objectives, policies)`), its actor mixed from the chosen specialists
    (`chosen_specialists`) and evaluated on `eval_episodes` episodes (`envs`, at least that many).

    An interpolated member's record: origin "interpolated", target_weight its mixing weights
    w, parents the ids of the specialists mixed with w_i > 0, iteration j // per_iteration + 1
    for grid point j (so its hypervolume curve is on the iteration axis of a MAPEX run making
    per_iteration children an iteration), env_samples the env frames of every evaluation so
    far: its only cost. Raises ValueError (one line) when the specialists' actors cannot be
    mixed (`starts_problem`), before any episode runs. `costs`, a list, receives the rows of
    pipeline.core.cost.COST_FIELDS: the starting policies' evaluation (phase "start"), then per
    iteration its grid points' mixing ("train") and evaluation (phase "interpolated").
    `make_mixer(actors)` returns the function w -> mixed actor (pipeline.core.alignment.mixer:
    aligned, repaired or RegMean mixes); its set-up (the alignment) is counted in the first grid
    point's "train" time. Default: the plain linear mix, `mix_actors`."""
    problem = starts_problem(starts)
    if problem is not None:
        raise ValueError(problem)
    members: list[Member] = []

    def add(actor: Actor, res: EvalResult, **record) -> None:
        samples = (members[-1].env_samples if members else 0) + res.env_samples
        members.append(
            Member(
                **record,
                returns=res.mean.tolist(),
                returns_std=res.std.tolist(),
                eval_episodes=eval_episodes,
                env_samples=samples,
                hidden_sizes=[m.out_features for m in actor.net if isinstance(m, torch.nn.Linear)][:-1],
                actor=actor_state(actor),
            )
        )
        if on_member is not None:
            on_member(members[-1])

    def run(actor: Actor, i: int) -> EvalResult:
        return evaluate_policy(actor, list(envs), eval_seeds(seed, EVAL_STREAM, i, eval_episodes))

    with Stopwatch() as ev:
        for i, s in enumerate(starts):
            add(
                s.actor,
                run(s.actor, i),
                origin="specialist",
                objective=s.objective,
                iteration=0,
                parents=[],
                target_weight=None,
                policy_name=s.name,
            )
    rows = [cost_row(0, "start", len(starts), None, ev)]
    chosen = chosen_specialists(starts, [m.returns for m in members], n_objectives)
    actors = [starts[i].actor for i in chosen]
    with Stopwatch() as setup:
        mix_of = make_mixer(actors) if make_mixer is not None else (lambda w: mix_actors(actors, w))
    for j, w in enumerate(mixing_weights(n_objectives, policies)):
        with Stopwatch() as mix:
            actor = mix_of(w)
        if j == 0:
            mix.wall += setup.wall
            mix.cpu += setup.cpu
        with Stopwatch() as ev:
            res = run(actor, len(members))
        it = j // per_iteration + 1
        if rows[-1]["iteration"] != it:
            rows.append(cost_row(it, ORIGIN, 0, None, None))
        row = rows[-1]
        row["policies"] += 1
        for key, sw in (("train", mix), ("eval", ev)):
            row[f"{key}_wall_s"] = round(row[f"{key}_wall_s"] + sw.wall, 4)
            row[f"{key}_cpu_s"] = round(row[f"{key}_cpu_s"] + sw.cpu, 4)
        add(
            actor,
            res,
            origin=ORIGIN,
            objective=None,
            iteration=it,
            parents=[i for i, x in zip(chosen, w) if x > 0],
            target_weight=list(w),
            policy_name=None,
        )
    if costs is not None:
        costs.extend(rows)
    return members
