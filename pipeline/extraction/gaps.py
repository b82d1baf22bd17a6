"""MAPEX step 1: gap identification, parent selection and the target weight (paper, section
"Method", "Step 1: Gap Identification and Parent Selection"), for any N >= 2 objectives.

Everything is measured in objective space normalised by the population's per-objective range
(pipeline.core.pareto.population_scale; see pipeline.extraction.mapex for why).

N = 2 (the paper): the non-dominated policies sorted along objective 0, edges between sorted
neighbours, one edge drawn by roulette on edge length, its 2 endpoints the parents
(`front_edges`, `select_edge_parents`: the code from before N >= 3 was supported, unchanged).

N >= 3 (an extension: the paper leaves it to future work): the front is triangulated
(pipeline.core.front_mesh: its points projected onto the hyperplane orthogonal to (1, ..., 1),
then Delaunay), one facet is drawn by roulette on its (N - 1)-dimensional volume, and its N
vertices are the parents (`front_facets`, `select_facet_parents`). For N = 2 this rule gives the
same edges as the paper's. With `extract.facet_bridge_ratio` (default 3; a further extension)
the roulette draws only from the gaps on the front's surface (`front_gaps`): facets spanning
the region between a thin curved front and its convex hull are eroded from the outside, and the
steps along what is left of such a front are gaps of 2 parents. Degenerate fronts
(docs/n_objectives.md):
- duplicate return vectors (after normalisation): one point, the lowest policy id, is kept;
- projections of lower affine rank r < N - 1 (fewer than N points, collinear for N = 3,
  coplanar for N = 4, ...): triangulated in their affine hull, so a facet, and the parents,
  are r + 1 policies (r = 1: edges between neighbours along the line, as for N = 2);
- a front of one point (r = 0), or no facet of positive size: the policies best on each
  objective over the whole population (argmax per column, first on ties) are the N parents,
  as N = 2 always did; no random draw is consumed then.

The target weight (`target_weight`) is the unit vector towards the centroid of the parents'
normalised returns, for any number of parents.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from pipeline.core.front_mesh import (
    edge_lengths,
    first_unique,
    regular_simplex_volume,
    simplex_volumes,
    surface,
    triangulate,
)
from pipeline.core.pareto import pareto_mask, population_scale

# ---------------------------------------------------------------- N = 2: the paper's edges


def front_edges(returns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Non-dominated policies sorted along objective 0, and the normalised lengths of the edges
    between sorted neighbours.

    returns: (n, 2). Result: ids (f,) and lengths (f - 1,), Euclidean in objective space scaled
    by the population's per-objective range.
    """
    if returns.shape[1] != 2:
        raise ValueError(f"gap identification is defined for 2 objectives (paper, Step 1), got {returns.shape[1]}")
    lo, span = population_scale(returns)
    ids = np.flatnonzero(pareto_mask(returns))
    # Ties on objective 0 are broken by objective 1 so the order is total and reproducible.
    ids = ids[np.lexsort((returns[ids, 1], returns[ids, 0]))]
    norm = (returns[ids] - lo) / span
    return ids, np.linalg.norm(np.diff(norm, axis=0), axis=1)


def select_edge_parents(returns: np.ndarray, rng: np.random.Generator) -> tuple[int, int]:
    """N = 2: draw one front edge with probability proportional to its normalised length
    (roulette wheel, paper Step 1) and return its two endpoint policy ids.

    If the front has no edge of positive length (one policy dominates all others), the two
    policies that are best on each objective are used as parents.
    """
    ids, lengths = front_edges(returns)
    total = lengths.sum() if len(lengths) else 0.0
    if total <= 0:
        return int(np.argmax(returns[:, 0])), int(np.argmax(returns[:, 1]))
    e = int(rng.choice(len(lengths), p=lengths / total))
    return int(ids[e]), int(ids[e + 1])


# ---------------------------------------------------------------- N >= 3: facets of the front mesh


def front_facets(returns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The facets of the non-dominated policies' mesh and their sizes, in normalised objective
    space (returns (n, m), m >= 2; used for m >= 3).

    Result: facets (F, k) policy ids, each row ascending, rows in lexicographic order, k = r + 1
    for projections of affine rank r (k = m for a front in general position); sizes (F,): the
    (k - 1)-dimensional volume of each facet's simplex in the normalised m-d space. Policies
    with the same normalised returns are one point, the lowest id. No facet ((0, 1), (0,)) for
    a front of one point.
    """
    ids, norm, facets = _front_mesh(returns)
    # ids ascending, so mapping indices to ids keeps the canonical order
    return ids[facets], simplex_volumes(norm, facets)


def _front_mesh(returns: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The front's distinct points and their mesh: policy ids (ascending), their normalised
    returns, and the facets as indices into them (see `front_facets`)."""
    lo, span = population_scale(returns)
    ids = np.flatnonzero(pareto_mask(returns))
    norm = (returns[ids] - lo) / span
    keep = first_unique(norm)  # ids ascending: the first of equal rows is the lowest id
    ids, norm = ids[keep], norm[keep]
    return ids, norm, triangulate(norm)


def best_per_objective(returns: np.ndarray) -> tuple[int, ...]:
    """The policy best on each objective over the whole population (argmax per column, the
    lowest id on ties): m ids, possibly repeated."""
    return tuple(int(np.argmax(returns[:, j])) for j in range(returns.shape[1]))


def front_gaps(returns: np.ndarray, bridge_ratio: float | None = None) -> tuple[list[tuple[int, ...]], np.ndarray]:
    """The gaps the roulette draws from for m >= 3 objectives: their policy ids and sizes.

    bridge_ratio None (the rule of `front_facets` alone): every facet of the front mesh, in
    `front_facets`' order, sized by its volume.

    bridge_ratio r (extract.facet_bridge_ratio; an extension, docs/n_objectives.md): only the
    gaps on the front's surface (all in pipeline.core.front_mesh.surface). In normalised
    objective space, an edge of the mesh *bridges* when the mesh's exposed boundary already joins
    its endpoints by a path of boundary edges each shorter than 1 / r of it: the edge cuts across
    a region the front goes around. The gaps are then
    - the facets left once those reached from outside the mesh through bridging edges are
      dropped (eroded from the outside inwards; enclosed holes are kept), each sized by its
      volume, in `front_facets`' order; then
    - the edges that do not bridge and belong to no kept facet (where the front is thin, the
      steps between neighbours along it), 2 parents each, sized as the regular
      simplex of the facets' dimension with that edge length (for m = 3 the equilateral
      triangle on it), so that they are in the facets' units; in lexicographic order.
    Should no gap of positive size remain, the whole mesh is used (as with None). Facets of 2
    vertices (a front whose projections are collinear) are kept as they are: there the mesh is
    already a chain of neighbours.
    """
    ids, norm, local = _front_mesh(returns)
    facets, sizes = ids[local], simplex_volumes(norm, local)  # = front_facets(returns)
    if bridge_ratio is None or len(facets) == 0 or facets.shape[1] < 3:
        return [tuple(int(i) for i in f) for f in facets], sizes
    keep, loose = surface(norm, local, bridge_ratio)
    loose_sizes = regular_simplex_volume(edge_lengths(norm, loose), facets.shape[1] - 1)
    gaps = [tuple(int(i) for i in f) for f in facets[keep]] + [tuple(int(i) for i in ids[e]) for e in loose]
    gap_sizes = np.concatenate([sizes[keep], loose_sizes])
    if not gap_sizes.sum() > 0:  # the rule never removes the last gap: the whole mesh
        return [tuple(int(i) for i in f) for f in facets], sizes
    return gaps, gap_sizes


def select_facet_parents(
    returns: np.ndarray, rng: np.random.Generator, bridge_ratio: float | None = None
) -> tuple[int, ...]:
    """Draw one gap of the front mesh (`front_gaps`: every facet for `bridge_ratio` None, the
    gaps on the front's surface otherwise) with probability proportional to its size (one
    roulette draw, as for N = 2) and return its vertices' policy ids, ascending.

    If there is no gap of positive size (a front of one point), the policies best on each
    objective are the parents (`best_per_objective`) and nothing is drawn from `rng`.
    """
    gaps, sizes = front_gaps(returns, bridge_ratio)
    total = sizes.sum() if len(sizes) else 0.0
    if total <= 0:
        return best_per_objective(returns)
    f = int(rng.choice(len(sizes), p=sizes / total))
    return gaps[f]


def select_parents(returns: np.ndarray, rng: np.random.Generator, bridge_ratio: float | None = None) -> tuple[int, ...]:
    """The parents of a child (paper Step 1) from the population's returns (n, m): by edge
    roulette for m = 2 (`select_edge_parents`: the paper's rule; `bridge_ratio` is not read),
    by roulette over the front mesh's gaps for m >= 3 (`select_facet_parents`, `bridge_ratio`
    as in `front_gaps`). Raises ValueError for m < 2."""
    m = returns.shape[1]
    if m == 2:
        return select_edge_parents(returns, rng)
    if m < 2:
        raise ValueError(f"gap identification needs at least 2 objectives, got {m}")
    return select_facet_parents(returns, rng, bridge_ratio)


# ---------------------------------------------------------------- the target weight


def target_weight(returns: np.ndarray, parents: Sequence[int], norm: str = "l2") -> np.ndarray:
    """Unit target weight towards the centroid of the parents' normalised returns (paper Step 1).

    Returns are scaled to [0, 1] by the population's per-objective range before the centroid is
    taken; the centroid is divided by its L2 norm (paper) or L1 sum (precursor). A zero centroid
    gives the uniform weight. Any number of parents.
    """
    lo, span = population_scale(returns)
    centroid = ((returns[list(parents)] - lo) / span).mean(axis=0)
    size = np.linalg.norm(centroid) if norm == "l2" else np.abs(centroid).sum()
    if size <= 1e-12:
        m = returns.shape[1]
        return np.full(m, 1 / np.sqrt(m) if norm == "l2" else 1 / m)
    return centroid / size
