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
same edges as the paper's. Degenerate fronts (docs/n_objectives.md):
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

from pipeline.core.front_mesh import first_unique, simplex_volumes, triangulate
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
    lo, span = population_scale(returns)
    ids = np.flatnonzero(pareto_mask(returns))
    norm = (returns[ids] - lo) / span
    keep = first_unique(norm)  # ids ascending: the first of equal rows is the lowest id
    ids, norm = ids[keep], norm[keep]
    facets = triangulate(norm)
    # ids ascending, so mapping indices to ids keeps the canonical order
    return ids[facets], simplex_volumes(norm, facets)


def best_per_objective(returns: np.ndarray) -> tuple[int, ...]:
    """The policy best on each objective over the whole population (argmax per column, the
    lowest id on ties): m ids, possibly repeated."""
    return tuple(int(np.argmax(returns[:, j])) for j in range(returns.shape[1]))


def select_facet_parents(returns: np.ndarray, rng: np.random.Generator) -> tuple[int, ...]:
    """Draw one facet of the front mesh with probability proportional to its size (one roulette
    draw, as for N = 2) and return its vertices' policy ids, ascending.

    If there is no facet of positive size (a front of one point), the policies best on each
    objective are the parents (`best_per_objective`) and nothing is drawn from `rng`.
    """
    facets, sizes = front_facets(returns)
    total = sizes.sum() if len(sizes) else 0.0
    if total <= 0:
        return best_per_objective(returns)
    f = int(rng.choice(len(sizes), p=sizes / total))
    return tuple(int(i) for i in facets[f])


def select_parents(returns: np.ndarray, rng: np.random.Generator) -> tuple[int, ...]:
    """The parents of a child (paper Step 1) from the population's returns (n, m): by edge
    roulette for m = 2 (`select_edge_parents`), by facet roulette for m >= 3
    (`select_facet_parents`). Raises ValueError for m < 2."""
    m = returns.shape[1]
    if m == 2:
        return select_edge_parents(returns, rng)
    if m < 2:
        raise ValueError(f"gap identification needs at least 2 objectives, got {m}")
    return select_facet_parents(returns, rng)


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
