"""Weight-space mixing of actors: the simplex grid of mixing weights and the mix itself.

Shared by the interpolation baseline (pipeline/baselines/interpolate.py, which documents the
method and its grid) and by MAPEX's hybrid extraction (pipeline/extraction: `extract.init:
interpolate` starts a child from its parents' mix, `extract.seed_interpolation` seeds the
population with the grid's policies). It lives in core because extraction may not import a
baseline (docs/developing.md, "The layers").

Mixing actors of one architecture: theta = sum_i w_i theta_i for a weight vector w on the
simplex ("rewarded soups", Rame et al. 2023). The grid: the points w = k / H of the simplex
lattice of resolution H (k non-negative integers summing to H) other than its N vertices, with
H the finest resolution whose non-vertex points number at most `policies`.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch

from pipeline.core.nets import Actor, NormalizedActor
from pipeline.core.specialist import StartingPolicy


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
    the same parameter names and shapes and the same action bounds; `NormalizedActor`s (imported
    with observation statistics) mix with each other only, and only with the same statistics
    (weights that read inputs of different scales do not mix)."""
    for actor, name in zip(actors, names):
        if type(actor) not in (Actor, NormalizedActor):
            return f"{name} is a {type(actor).__name__} (a program brought in whole), which has no weights to mix"
    if len({type(a) for a in actors}) > 1:
        normalized = [n for a, n in zip(actors, names) if isinstance(a, NormalizedActor)]
        return (
            f"{', '.join(normalized)} normalise observations with statistics and the others do not: their weights "
            "read inputs of different scales"
        )
    ref, ref_name = actors[0].state_dict(), names[0]
    for actor, name in zip(actors[1:], names[1:]):
        state = actor.state_dict()
        if list(state) != list(ref) or any(state[k].shape != ref[k].shape for k in ref):
            shapes = lambda s: [tuple(v.shape) for k, v in s.items() if k.endswith("weight")]  # noqa: E731
            return (
                f"{ref_name} has layers {shapes(ref)} and {name} {shapes(state)}: "
                "interpolation needs actors of one architecture"
            )
        differ = [k for k, _ in actor.named_buffers() if not torch.equal(state[k], ref[k])]
        if differ:
            what = "observation statistics" if any(k.startswith("obs_") for k in differ) else "action bounds"
            return f"{ref_name} and {name} differ in their {what} ({', '.join(differ)})"
    return None


@torch.no_grad()
def mix_actors(actors: Sequence[Actor], weights: Sequence[float]) -> Actor:
    """A new actor with parameters sum_i weights[i] * theta_i (float32, in order; a zero weight
    adds nothing, so a vertex w = e_k reproduces actor k's parameters exactly). Buffers (the
    action bounds; a `NormalizedActor`'s statistics) are the first actor's, and so is its class;
    every actor must pass `architecture_problem`."""
    if len(actors) != len(weights) or not actors:
        raise ValueError(f"{len(actors)} actors and {len(weights)} weights")
    problem = architecture_problem(actors, [f"actor {i}" for i in range(len(actors))])
    if problem is not None:
        raise ValueError(problem)
    first = actors[0]
    with torch.random.fork_rng(devices=[]):  # building an Actor draws an init we overwrite
        out = type(first)(
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
