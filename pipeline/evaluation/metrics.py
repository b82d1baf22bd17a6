"""Quality indicators of a Pareto-front approximation. Maximisation everywhere; numpy in, floats out.

`points` is always an (n, m) array of return vectors (n policies, m objectives). Functions
named after a front indicator (sparsity, expected utility, ...) take the points as given: pass
the non-dominated set (`pipeline.core.pareto.pareto_mask`) when the front is meant. `front_metrics`
bundles all of them for one front, as the evaluate stage reports them.

Definitions (and where they come from):

- hypervolume: `pipeline.core.pareto.hypervolume` (pymoo, exact), bounded below by a fixed reference
  point per env (params `env.reference_point`).
- hv_fraction: hypervolume / volume of the box [ref, ideal]; with the ideal point of the front
  itself it measures how much of its own bounding box a front fills (1 for a single point).
- sparsity: the paper's Table 1 caption: "the average Euclidean distance between neighbouring
  points". For 2 objectives, neighbours along the front sorted by objective 0. For N >= 3
  (an extension, docs/n_objectives.md), neighbours = the edges of the front's mesh
  (pipeline.core.front_mesh: the front scaled by its own per-objective range, projected onto
  the hyperplane orthogonal to (1, ..., 1) and Delaunay-triangulated), each edge once. Raw
  return units either way, so only comparable within one env. Lower is denser.
- sparsity_pgmorl: PGMORL's indicator (Xu et al. 2020), used by the precursor and MOPDERL code:
  sort the front along each objective separately, sum the squared gaps between neighbours over
  all objectives, divide by n - 1. Squared units: not comparable with the paper's Table 1.
- expected_utility: mean over evenly spread weight vectors w on the simplex of max_p w . J_p,
  on raw (unnormalised) returns, as morl-baselines computes it. On raw returns the objective
  with the larger scale (e.g. HalfCheetah's energy, thousands) weighs more; compare EU only
  between methods on the same env.
- cardinality: the number of distinct non-dominated return vectors.
- distinct_count: non-dominated points that stay distinct when points closer than `tol` of the
  normalised objective range are merged (resolution-limited cardinality).
- hypervolume_history: the hypervolume of the population as it grew, one value per extraction
  iteration, against iteration and cumulative env samples (the paper's learning curves).
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from pipeline.core.front_mesh import first_unique, mesh_edges, triangulate
from pipeline.core.pareto import hypervolume as _pareto_hypervolume
from pipeline.core.pareto import ideal_box_volume, pareto_mask, population_scale


def _as_points(points: np.ndarray, m: int | None = None) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    if p.ndim == 1 and p.size == 0:
        p = p.reshape(0, m or 0)
    if p.ndim != 2:
        raise ValueError(f"points must be (n, m), got shape {p.shape}")
    if m is not None and p.shape[1] != m:
        raise ValueError(f"points have {p.shape[1]} objectives, expected {m}")
    return p


def non_dominated(points: np.ndarray) -> np.ndarray:
    """The distinct non-dominated rows of `points` (k, m), sorted lexicographically (objective 0 first)."""
    p = _as_points(points)
    if len(p) == 0:
        return p
    front = np.unique(p[pareto_mask(p)], axis=0)  # np.unique sorts rows lexicographically
    return front


def hypervolume(points: np.ndarray, ref: np.ndarray | list[float]) -> float:
    """Hypervolume of `points` (n, m) above the reference point `ref` (m,). See pipeline.core.pareto."""
    ref = np.asarray(ref, dtype=float)
    p = _as_points(points, len(ref))
    return _pareto_hypervolume(p, ref) if len(p) else 0.0


def ideal_point(points: np.ndarray) -> np.ndarray:
    """Per-objective maximum of `points` (n >= 1, m) -> (m,)."""
    p = _as_points(points)
    if len(p) == 0:
        raise ValueError("the ideal point of an empty set is undefined")
    return p.max(axis=0)


def hv_fraction(points: np.ndarray, ref: np.ndarray | list[float], ideal: np.ndarray | None = None) -> float:
    """Hypervolume of `points` as a fraction of the box between `ref` and `ideal` (m,).

    `ideal` defaults to the per-objective maximum of `points`, so the result is in [0, 1].
    With a fixed, shared ideal (the evaluate stage uses the ideal of the whole re-evaluated
    population for the front and for the specialists alike) fractions compare like hypervolumes.
    Returns 0 for an empty set or an empty box.
    """
    ref = np.asarray(ref, dtype=float)
    p = _as_points(points, len(ref))
    if len(p) == 0:
        return 0.0
    box = ideal_box_volume(ideal_point(p) if ideal is None else np.asarray(ideal, float), ref)
    return hypervolume(p, ref) / box if box > 0 else 0.0


def sparsity(points: np.ndarray) -> float:
    """The paper's sparsity (Table 1 caption): mean Euclidean distance between neighbouring
    points of `points` (n, m), in raw units. 0 for n < 2.

    m <= 2: neighbours along the order of objective 0 (ties broken by the others); a repeated
    point is a neighbour at distance 0. For n evenly spaced points on a segment from a to b:
    |b - a| / (n - 1).
    m >= 3: the mean length of the distinct edges of the front mesh (`mesh_sparsity`).
    """
    p = _as_points(points)
    if len(p) < 2:
        return 0.0
    if p.shape[1] >= 3:
        return mesh_sparsity(p)
    order = np.lexsort(p.T[::-1])  # by objective 0, then 1, ...
    return float(np.linalg.norm(np.diff(p[order], axis=0), axis=1).mean())


def mesh_sparsity(points: np.ndarray) -> float:
    """Mean Euclidean length, in raw units, of the distinct edges of the mesh over `points`
    (n, m >= 2): the paper's sparsity for N >= 3 objectives (docs/n_objectives.md).

    The mesh's topology is computed with the points scaled to [0, 1] by their own per-objective
    range (pipeline.core.front_mesh.triangulate: projection onto the hyperplane orthogonal to
    (1, ..., 1), Delaunay; lower-rank fronts in their affine hull, collinear ones as a chain).
    Repeated points are merged first. The points should be mutually non-dominated (a front,
    as `front_metrics` passes it). 0 when there is no edge (fewer than 2 distinct points).
    For n evenly spaced points on a segment from a to b: |b - a| / (n - 1), as for m = 2.
    """
    p = _as_points(points)
    p = p[first_unique(p)]
    if len(p) < 2:
        return 0.0
    lo, span = population_scale(p)
    edges = mesh_edges(triangulate((p - lo) / span))
    if len(edges) == 0:
        return 0.0
    return float(np.linalg.norm(p[edges[:, 1]] - p[edges[:, 0]], axis=1).mean())


def sparsity_pgmorl(points: np.ndarray) -> float:
    """PGMORL sparsity of a front `points` (n, m): (1 / (n - 1)) sum_j sum_i (P_j[i+1] - P_j[i])^2,

    where P_j is objective j of the points sorted along objective j alone. 0 for n < 2.
    For n evenly spaced points on a segment from a to b: |b - a|^2 / (n - 1)^2.
    """
    p = _as_points(points)
    n = len(p)
    if n < 2:
        return 0.0
    gaps = np.diff(np.sort(p, axis=0), axis=0)  # sorts each column independently
    return float((gaps**2).sum() / (n - 1))


def simplex_weights(m: int, n: int) -> np.ndarray:
    """At least `n` weight vectors evenly spread on the (m-1)-simplex -> (k, m), rows sum to 1.

    m = 2: exactly n vectors (i / (n-1), 1 - i / (n-1)). m > 2: the Das-Dennis lattice with the
    fewest divisions H giving at least n vectors (all w with w_j = c_j / H, sum c_j = H).
    """
    if m < 1 or n < 1:
        raise ValueError(f"need m >= 1 and n >= 1, got m={m}, n={n}")
    if m == 1:
        return np.ones((1, 1))
    if m == 2:
        if n == 1:
            return np.full((1, 2), 0.5)
        t = np.linspace(0.0, 1.0, n)
        return np.stack([t, 1.0 - t], axis=1)
    h = 1
    while math.comb(h + m - 1, m - 1) < n:
        h += 1
    rows = []
    # stars and bars: m - 1 bar positions among h + m - 1 slots
    for bars in itertools.combinations(range(h + m - 1), m - 1):
        edges = (-1, *bars, h + m - 1)
        rows.append([edges[i + 1] - edges[i] - 1 for i in range(m)])
    return np.asarray(rows, dtype=float) / h


def expected_utility(points: np.ndarray, weights: np.ndarray | None = None, n_weights: int = 100) -> float:
    """Expected linear utility of a front on raw returns: mean_w max_p w . J_p.

    `weights` (k, m) default to `simplex_weights(m, n_weights)`. Raises on an empty set
    (the utility of no policy is undefined).
    """
    p = _as_points(points)
    if len(p) == 0:
        raise ValueError("expected utility of an empty set is undefined")
    w = simplex_weights(p.shape[1], n_weights) if weights is None else np.asarray(weights, dtype=float)
    if w.ndim != 2 or w.shape[1] != p.shape[1]:
        raise ValueError(f"weights must be (k, {p.shape[1]}), got shape {w.shape}")
    return float((w @ p.T).max(axis=1).mean())


def cardinality(points: np.ndarray) -> int:
    """Number of distinct non-dominated return vectors among `points`."""
    return int(len(non_dominated(points)))


def distinct_count(points: np.ndarray, lo: np.ndarray, hi: np.ndarray, tol: float = 0.02) -> int:
    """Number of distinct non-dominated points at resolution `tol`.

    Objective j is normalised as (x_j - lo_j) / (hi_j - lo_j) (a zero range counts as 1). The
    non-dominated points, sorted lexicographically, are merged greedily: a point is kept when its
    Euclidean distance to every point kept so far is >= tol, otherwise it merges into that one.
    The result does not depend on the input order and is <= cardinality(points).
    """
    if not tol > 0:
        raise ValueError(f"tol must be > 0, got {tol}")
    front = non_dominated(points)
    if len(front) == 0:
        return 0
    span = np.asarray(hi, float) - np.asarray(lo, float)
    span = np.where(span > 0, span, 1.0)
    z = (front - np.asarray(lo, float)) / span
    kept: list[np.ndarray] = []
    for q in z:
        if all(np.linalg.norm(q - k) >= tol for k in kept):
            kept.append(q)
    return len(kept)


def front_metrics(
    points: np.ndarray,
    ref: np.ndarray | list[float],
    ideal: np.ndarray,
    tol: float = 0.02,
    n_weights: int = 100,
) -> dict[str, float | int]:
    """Every indicator of the non-dominated set of `points` (n, m), with a fixed `ref` and `ideal`.

    The box [ref, ideal] serves both hv_fraction and distinct_count's normalisation. An empty
    set gives zeros (and expected_utility NaN).
    """
    ref = np.asarray(ref, dtype=float)
    p = _as_points(points, len(ref))
    front = non_dominated(p)
    return {
        "hypervolume": hypervolume(front, ref),
        "hv_fraction": hv_fraction(front, ref, ideal) if len(front) else 0.0,
        "sparsity": sparsity(front),
        "sparsity_pgmorl": sparsity_pgmorl(front),
        "expected_utility": expected_utility(front, n_weights=n_weights) if len(front) else float("nan"),
        "cardinality": int(len(front)),
        "distinct_count": distinct_count(front, ref, ideal, tol),
    }


def mean_sem(values: np.ndarray | list[float]) -> tuple[float, float]:
    """Mean and standard error of the mean (std with ddof=1 over sqrt(n)); SEM is NaN for n < 2."""
    v = np.asarray(values, dtype=float)
    if v.size == 0:
        return float("nan"), float("nan")
    sem = float(v.std(ddof=1) / math.sqrt(v.size)) if v.size > 1 else float("nan")
    return float(v.mean()), sem


def population_summary(
    returns: np.ndarray,
    is_specialist: np.ndarray,
    ref: np.ndarray | list[float],
    tol: float = 0.02,
    n_weights: int = 100,
) -> dict:
    """Front metrics of a whole population and of its specialists alone, on one shared box.

    returns (n, m): one return vector per member; is_specialist (n,) bool. The ideal point is the
    per-objective maximum over the whole population (= over its front), used by both sets so
    their hv_fraction and distinct_count are on the same scale. `hv_ratio_vs_specialists` is
    HV(front) / HV(specialists), None when the specialists' HV is 0 (undefined ratio).
    """
    ref = np.asarray(ref, dtype=float)
    r = _as_points(returns, len(ref))
    spec = np.asarray(is_specialist, dtype=bool)
    if len(r) == 0:
        raise ValueError("population is empty")
    if spec.shape != (len(r),):
        raise ValueError(f"is_specialist has shape {spec.shape}, expected ({len(r)},)")
    ideal = ideal_point(r)
    front = front_metrics(r, ref, ideal, tol, n_weights)
    specialists = front_metrics(r[spec], ref, ideal, tol, n_weights)
    hv_s = specialists["hypervolume"]
    return {
        "front": front,
        "specialists": specialists,
        "hv_ratio_vs_specialists": front["hypervolume"] / hv_s if hv_s > 0 else None,
        "ideal_point": ideal.tolist(),
        "outside_reference": int((~(r > ref).all(axis=1)).sum()),
    }


def hypervolume_history(
    iteration: np.ndarray,
    env_samples: np.ndarray,
    returns: dict[str, np.ndarray],
    ref: np.ndarray | list[float],
) -> dict[str, np.ndarray]:
    """Hypervolume of the population after each iteration, for one or more sets of returns.

    iteration (n,): the iteration that made each member (0 for specialists); env_samples (n,):
    cumulative env samples once the member was evaluated; returns: column name -> (n, m)
    return vectors of the same members (e.g. extraction-time and re-evaluated). For each
    iteration t present, the population is every member with iteration <= t. Returns columns
    of length T (the distinct iterations, ascending): `iteration`, `population` (members),
    `env_samples` (the most any of them had used) and one hypervolume column per entry of
    `returns`, each above `ref`.
    """
    it = np.asarray(iteration)
    samples = np.asarray(env_samples)
    ref = np.asarray(ref, dtype=float)
    points = {name: _as_points(r, len(ref)) for name, r in returns.items()}
    if it.ndim != 1 or samples.shape != it.shape or any(len(p) != len(it) for p in points.values()):
        raise ValueError(
            f"iteration {it.shape}, env_samples {samples.shape} and returns "
            f"{ {k: p.shape for k, p in points.items()} } must describe the same members"
        )
    steps = np.unique(it)
    upto = [it <= t for t in steps]
    out = {
        "iteration": steps,
        "population": np.array([m.sum() for m in upto]),
        "env_samples": np.array([samples[m].max() for m in upto]),
    }
    for name, p in points.items():
        out[name] = np.array([hypervolume(p[m], ref) for m in upto])
    return out
