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

import math
from typing import Callable, Sequence

import gymnasium as gym
import torch

from pipeline.core.nets import Actor
from pipeline.core.population import Member, actor_state
from pipeline.core.specialist import StartingPolicy
from pipeline.evaluation.episodes import EvalResult, eval_seeds, evaluate_policy

# Extraction's evaluation stream (pipeline.extraction.run.EVAL_STREAM; a test checks they agree),
# so member i is evaluated on the episodes MAPEX's member i is: the starting policies get the
# returns MAPEX's population starts with, and interpolated policy j those of MAPEX's child j.
EVAL_STREAM = 0
ORIGIN = "interpolated"  # the members' origin in population.pt (the starting policies': "specialist")


def simplex_points(n_objectives: int, resolution: int) -> list[tuple[int, ...]]:
    """The lattice points k (non-negative integers summing to `resolution`) of the simplex of
    `n_objectives` vertices, without the vertices; ordered by their last coordinate, then the
    one before, ... (for N = 2: l = k_1 / H ascending, from A towards B)."""
    if n_objectives < 2 or resolution < 1:
        raise ValueError(f"a simplex grid needs >= 2 objectives and resolution >= 1, got {n_objectives}, {resolution}")

    def compositions(n: int, total: int):
        if n == 1:
            yield (total,)
            return
        for first in range(total, -1, -1):
            for rest in compositions(n - 1, total - first):
                yield (first, *rest)

    points = [k for k in compositions(n_objectives, resolution) if max(k) < resolution]
    return sorted(points, key=lambda k: k[::-1])


def non_vertex_count(n_objectives: int, resolution: int) -> int:
    """How many lattice points of resolution H the simplex has, its vertices left out."""
    return math.comb(resolution + n_objectives - 1, n_objectives - 1) - n_objectives


def grid_resolution(n_objectives: int, policies: int) -> int:
    """The finest resolution H >= 1 whose non-vertex lattice points number at most `policies`."""
    if policies < 0:
        raise ValueError(f"policies must be >= 0, got {policies}")
    h = 1
    while non_vertex_count(n_objectives, h + 1) <= policies:
        h += 1
    return h


def mixing_weights(n_objectives: int, policies: int) -> list[list[float]]:
    """The grid's mixing weights w (each summing to 1, one weight per specialist), in order."""
    h = grid_resolution(n_objectives, policies)
    return [[ki / h for ki in k] for k in simplex_points(n_objectives, h)]


def architecture_problem(actors: Sequence[torch.nn.Module], names: Sequence[str]) -> str | None:
    """Why the actors' weights cannot be mixed (None if they can): each must be an MLP `Actor`
    (not a TorchScript or torch.export program, whose weights are not open to mixing), all with
    the same parameter names and shapes and the same action bounds."""
    for actor, name in zip(actors, names):
        if type(actor) is not Actor:
            return f"{name} is a {type(actor).__name__} (a program brought in whole), which has no weights to mix"
    ref, ref_name = actors[0].state_dict(), names[0]
    for actor, name in zip(actors[1:], names[1:]):
        state = actor.state_dict()
        if list(state) != list(ref) or any(state[k].shape != ref[k].shape for k in ref):
            shapes = lambda s: [tuple(v.shape) for k, v in s.items() if k.endswith("weight")]  # noqa: E731
            return (
                f"{ref_name} has layers {shapes(ref)} and {name} {shapes(state)}: "
                "interpolation needs actors of one architecture"
            )
        buffers = [k for k, _ in actor.named_buffers()]
        if any(not torch.equal(state[k], ref[k]) for k in buffers):
            return f"{ref_name} and {name} differ in their action bounds ({', '.join(buffers)})"
    return None


@torch.no_grad()
def mix_actors(actors: Sequence[Actor], weights: Sequence[float]) -> Actor:
    """A new actor with parameters sum_i weights[i] * theta_i (float32, in order; a zero weight
    adds nothing, so a vertex w = e_k reproduces actor k's parameters exactly). Buffers (the
    action bounds) are the first actor's; every actor must pass `architecture_problem`."""
    if len(actors) != len(weights) or not actors:
        raise ValueError(f"{len(actors)} actors and {len(weights)} weights")
    problem = architecture_problem(actors, [f"actor {i}" for i in range(len(actors))])
    if problem is not None:
        raise ValueError(problem)
    first = actors[0]
    with torch.random.fork_rng(devices=[]):  # building an Actor draws an init we overwrite
        out = Actor(
            first.net[0].in_features,
            first.net[-1].out_features,
            [m.out_features for m in first.net if isinstance(m, torch.nn.Linear)][:-1],
            (first.centre - first.scale).cpu(),
            (first.centre + first.scale).cpu(),
        )
    states = [a.state_dict() for a in actors]
    params = {k for k, _ in first.named_parameters()}
    mixed = {}
    for key, value in states[0].items():
        if key not in params:
            mixed[key] = value.detach().cpu().clone()
            continue
        total = torch.zeros_like(value, device="cpu")
        for w, state in zip(weights, states):
            if w != 0:
                total += float(w) * state[key].detach().cpu()
        mixed[key] = total
    out.load_state_dict(mixed)
    return out.eval()


def starts_problem(starts: Sequence[StartingPolicy]) -> str | None:
    """Why the starting policies cannot be mixed (`architecture_problem`), None if they can."""
    return architecture_problem(
        [s.actor for s in starts], [f"objective {s.objective}'s policy {s.name!r}" for s in starts]
    )


def chosen_specialists(
    starts: Sequence[StartingPolicy], returns: Sequence[Sequence[float]], n_objectives: int
) -> list[int]:
    """Per objective k, the index of the starting policy that is mixed as specialist k: of the
    policies of objective k's set (one for a TD3 or imported specialist, a PDERL population and
    its RL actor), the one with the highest evaluated return on objective k (the first on ties)."""
    chosen = []
    for k in range(n_objectives):
        mine = [i for i, s in enumerate(starts) if s.objective == k]
        if not mine:
            raise ValueError(f"no starting policy of objective {k}")
        chosen.append(max(mine, key=lambda i: (returns[i][k], -i)))
    return chosen


def interpolate(
    starts: Sequence[StartingPolicy],
    n_objectives: int,
    policies: int,
    per_iteration: int,
    eval_episodes: int,
    seed: int,
    envs: Sequence[gym.Env],
    on_member: Callable[[Member], None] | None = None,
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
    mixed (`starts_problem`), before any episode runs."""
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
    chosen = chosen_specialists(starts, [m.returns for m in members], n_objectives)
    actors = [starts[i].actor for i in chosen]
    for j, w in enumerate(mixing_weights(n_objectives, policies)):
        actor = mix_actors(actors, w)
        add(
            actor,
            run(actor, len(members)),
            origin=ORIGIN,
            objective=None,
            iteration=j // per_iteration + 1,
            parents=[i for i, x in zip(chosen, w) if x > 0],
            target_weight=list(w),
            policy_name=None,
        )
    return members
