"""A mesh over a Pareto front of N >= 2 objectives: which front points are neighbours.

Shared by MAPEX's gap identification for N >= 3 objectives (pipeline.extraction.gaps) and the
paper's sparsity in N dimensions (pipeline.evaluation.metrics); docs/n_objectives.md explains
the rule. Everything here works on points already scaled to comparable units (the caller
normalises) and on indices into the array it is given; nothing here knows about policies.

The mesh. A set of distinct, mutually non-dominated points in R^N is projected orthogonally
onto the hyperplane H = {x : sum(x) = 0} orthogonal to the diagonal (1, ..., 1), written in an
orthonormal basis of H (N - 1 coordinates), and the projected points are Delaunay-triangulated
(scipy.spatial.Delaunay, i.e. qhull). Each simplex is a facet of the front; its vertices are
the corresponding front points.

Why the projection is injective on such a set: the projection of x is x - mean(x) (1, ..., 1),
so two points a, b have the same projection iff a - b = c (1, ..., 1) for some real c. If c > 0,
a exceeds b by c in every objective and dominates it; if c < 0, b dominates a; if c = 0, a = b.
Distinct mutually non-dominated points therefore have distinct projections, and the front is
the graph of a function over (part of) H: triangulating the projections triangulates the front
itself, with no fold and no two front points stacked on one projected point. For N = 2, H is
the line through (1, -1): the projected coordinate (x0 - x1) / sqrt(2) grows strictly along a
front sorted by objective 0 (x0 up means x1 down), so the 1-d triangulation is the chain of
neighbours along objective 0, the paper's edges.

Degenerate inputs never reach qhull. The affine rank r of the projected points (their spread
in H) is computed first, from the singular values of the centred projections: a direction
counts if its singular value exceeds RANK_RTOL times the largest (and RANK_ATOL absolute).
- r = N - 1 (full rank): Delaunay of the projections in the fixed basis of H;
- 2 <= r < N - 1 (e.g. 4 coplanar projections for N = 4): Delaunay in the r principal
  coordinates of their affine hull, so facets have r + 1 vertices;
- r = 1 (collinear projections, e.g. any 2 points): sorted along the line, consecutive points
  joined by edges (2 vertices per facet), no qhull;
- r = 0 (one point, or points that coincide to within RANK_ATOL): no facet;
- r + 1 points of rank r: the single simplex they span, no qhull.
Qhull runs with fixed options (QHULL_OPTIONS, no joggle "QJ") on full-rank input; should it
still find the input too flat, the smallest principal direction is dropped and the points are
triangulated one rank lower (ending, at worst, at the chain of r = 1). Points that qhull merges
as (near-)duplicates ("Qc": coplanar points) are vertices of no facet.

Facet size = the r-dimensional volume of the simplex its vertices span in the space of the
given points (not of the projections): sqrt(det(G)) / r!, G the Gram matrix of the edge
vectors v_i - v_0. For an edge (r = 1) that is its Euclidean length.

Facets come back in a canonical order, independent of qhull's output order and of the signs
of singular vectors: each facet's vertex indices ascending, facets in lexicographic order.
"""

from __future__ import annotations

import math

import numpy as np

RANK_RTOL = 1e-9  # a principal direction of the projections counts if its singular value > RANK_RTOL * the largest
RANK_ATOL = 1e-12  # ... and > RANK_ATOL: points spread less than this in every direction are one point
QHULL_OPTIONS = "Qbb Qc Qz Q12"  # scipy's default Delaunay options spelled out (plus "Qx" above 4-d), never "QJ"


def diagonal_basis(m: int) -> np.ndarray:
    """An orthonormal basis of the hyperplane orthogonal to (1, ..., 1) in R^m: (m, m - 1).

    Column k (k = 1 .. m - 1) is (1, ..., 1, -k, 0, ..., 0) / sqrt(k (k + 1)) with k ones (the
    Helmert basis): closed form, so the projection needs no linear-algebra library call.
    """
    if m < 2:
        raise ValueError(f"a front mesh needs at least 2 objectives, got {m}")
    basis = np.zeros((m, m - 1))
    for k in range(1, m):
        basis[:k, k - 1] = 1.0
        basis[k, k - 1] = -float(k)
        basis[:, k - 1] /= math.sqrt(k * (k + 1))
    return basis


def project(points: np.ndarray) -> np.ndarray:
    """Coordinates (n, m - 1) of the points (n, m) projected onto the hyperplane orthogonal to
    (1, ..., 1), in the basis `diagonal_basis(m)`."""
    p = np.asarray(points, dtype=float)
    return p @ diagonal_basis(p.shape[1])


def first_unique(points: np.ndarray) -> np.ndarray:
    """Indices (ascending) of the first occurrence of each distinct row of `points` (n, m): of
    rows that are equal, only the lowest index is kept."""
    p = np.asarray(points, dtype=float)
    if len(p) == 0:
        return np.zeros(0, dtype=np.int64)
    _, first = np.unique(p, axis=0, return_index=True)
    return np.sort(first).astype(np.int64)


def affine_coordinates(y: np.ndarray) -> tuple[np.ndarray, int]:
    """The affine rank r of the rows of y (n, d) and coordinates (n, r) of them in their affine
    hull: y itself (centred) if r = d, else the r principal coordinates (see the module
    docstring for the tolerance)."""
    if len(y) < 2:
        return np.zeros((len(y), 0)), 0
    centred = y - y.mean(axis=0)
    u, s, _ = np.linalg.svd(centred, full_matrices=False)
    if s[0] <= RANK_ATOL:
        return np.zeros((len(y), 0)), 0
    r = int(np.sum(s > max(RANK_RTOL * s[0], RANK_ATOL)))
    if r == y.shape[1]:
        return centred, r  # full rank: keep the fixed basis (no dependence on singular vectors' signs)
    return _signed(u[:, :r]) * s[:r], r


def _signed(u: np.ndarray) -> np.ndarray:
    """Singular vectors (n, r) with each column's sign fixed: its entry of largest magnitude
    (the first such) positive, so the coordinates do not depend on the LAPACK build's choice."""
    pick = u[np.argmax(np.abs(u), axis=0), np.arange(u.shape[1])]
    return u * np.where(pick < 0, -1.0, 1.0)


def canonical(facets: np.ndarray) -> np.ndarray:
    """Facets (F, k) of vertex indices: each row sorted ascending, rows in lexicographic order,
    repeated rows dropped."""
    f = np.sort(np.asarray(facets, dtype=np.int64), axis=1)
    if len(f) == 0:
        return f
    return np.unique(f, axis=0)  # np.unique sorts rows lexicographically


def _chain(z: np.ndarray) -> np.ndarray:
    """Edges (n - 1, 2) between consecutive points of z (n, 1) sorted along the line (ties by index)."""
    order = np.lexsort((np.arange(len(z)), z[:, 0]))
    return np.stack([order[:-1], order[1:]], axis=1)


def _principal(y: np.ndarray, r: int) -> np.ndarray:
    """The r leading principal coordinates of the rows of y (n, d)."""
    centred = y - y.mean(axis=0)
    u, s, _ = np.linalg.svd(centred, full_matrices=False)
    return _signed(u[:, :r]) * s[:r]


def _simplices(z: np.ndarray, r: int) -> np.ndarray:
    """A triangulation (F, r' + 1) of points z (n, r) of affine rank r (r' = r unless qhull
    rejects the input, then lower: see the module docstring)."""
    from scipy.spatial import Delaunay, QhullError

    while r >= 2:
        if len(z) == r + 1:
            return np.arange(r + 1)[None, :]
        try:
            options = QHULL_OPTIONS + (" Qx" if r > 4 else "")
            return Delaunay(z, qhull_options=options).simplices
        except QhullError:
            r -= 1
            z = _principal(z, r)
    return _chain(z) if r == 1 else np.zeros((0, 1), dtype=np.int64)


def triangulate(points: np.ndarray) -> np.ndarray:
    """The facets of the mesh over `points` (n, m), m >= 2: (F, r + 1) indices into `points`,
    r the affine rank of their projections, in canonical order (see the module docstring).

    `points` should be distinct and mutually non-dominated (a front, already normalised): then
    the mesh covers every point. Other input never raises, but a dominated point may then
    share a projection with another and be left out of every facet. No facet (shape (0, 1))
    for fewer than 2 points or a rank of 0.
    """
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] < 2:
        raise ValueError(f"points must be (n, m) with m >= 2 objectives, got shape {p.shape}")
    if len(p) < 2:
        return np.zeros((0, 1), dtype=np.int64)
    z, r = affine_coordinates(project(p))
    if r == 0:
        return np.zeros((0, 1), dtype=np.int64)
    return canonical(_simplices(z, r))


def simplex_volumes(points: np.ndarray, facets: np.ndarray) -> np.ndarray:
    """The k-dimensional volume (F,) of each facet's simplex, k = facets.shape[1] - 1, in the
    space of `points` (n, m): sqrt(det(Gram)) / k! of its edge vectors from its first vertex.
    k = 1: the Euclidean length of the edge. 0 for a flat simplex."""
    p = np.asarray(points, dtype=float)
    f = np.asarray(facets, dtype=np.int64)
    if len(f) == 0 or f.shape[1] < 2:
        return np.zeros(len(f))
    k = f.shape[1] - 1
    edges = p[f[:, 1:]] - p[f[:, :1]]  # (F, k, m)
    if k == 1:
        return np.linalg.norm(edges[:, 0], axis=1)
    gram = edges @ edges.transpose(0, 2, 1)  # (F, k, k)
    return np.sqrt(np.clip(np.linalg.det(gram), 0.0, None)) / math.factorial(k)


def mesh_edges(facets: np.ndarray) -> np.ndarray:
    """The distinct edges (E, 2) of the facets (F, k): every pair of vertices of a facet, each
    pair once, (low, high) index, in lexicographic order. None for facets of one vertex."""
    f = np.asarray(facets, dtype=np.int64)
    if len(f) == 0 or f.shape[1] < 2:
        return np.zeros((0, 2), dtype=np.int64)
    k = f.shape[1]
    pairs = [f[:, [i, j]] for i in range(k) for j in range(i + 1, k)]
    return canonical(np.concatenate(pairs))


def edge_lengths(points: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """The Euclidean length (E,) of each edge (E, 2) between rows of `points` (n, m)."""
    p = np.asarray(points, dtype=float)
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    return np.linalg.norm(p[e[:, 0]] - p[e[:, 1]], axis=1)


def graph_minimax(points: np.ndarray, edges: np.ndarray, lengths: np.ndarray | None = None) -> np.ndarray:
    """(n, n) minimax path distances in the graph on the rows of `points` (n, m) with edges
    `edges` (E, 2), each as long as `lengths` (default: the Euclidean distance between its
    ends): for a and b, the least possible longest edge of a path from a to b in the graph; inf
    where there is no path, 0 on the diagonal. Kruskal's order: edges by length, and the first
    edge to join two components gives every pair across them its length (the values do not
    depend on how ties are ordered, and each is one of `lengths` exactly)."""
    n = len(points)
    out = np.full((n, n), np.inf)
    np.fill_diagonal(out, 0.0)
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    if len(e) == 0:
        return out
    length = edge_lengths(points, e) if lengths is None else np.asarray(lengths, dtype=float)
    root = list(range(n))
    members = {i: [i] for i in range(n)}
    for j in np.argsort(length, kind="stable").tolist():
        a, b = root[e[j, 0]], root[e[j, 1]]
        if a == b:
            continue
        if len(members[a]) < len(members[b]):
            a, b = b, a
        out[np.ix_(members[a], members[b])] = length[j]
        out[np.ix_(members[b], members[a])] = length[j]
        for i in members[b]:
            root[i] = a
        members[a].extend(members.pop(b))
    return out


def surface(points: np.ndarray, facets: np.ndarray, ratio: float | None) -> tuple[np.ndarray, np.ndarray]:
    """The part of the mesh over `points` (n, m) that lies on the front's surface: a mask (F,)
    of the facets (F, k) kept, and the loose edges (E, 2) (see below).

    The mesh triangulates the convex hull of the projected front, so where the front is curved
    and thin (an arc) it also covers the region between the front and the chord of its hull,
    with facets joining far-apart points across it. Those are eroded from the outside:

    - A ridge (a facet's face of k - 1 vertices) is *exposed* once fewer than 2 kept facets
      share it: at first the hull's boundary, then the faces each dropped facet uncovers.
    - An edge (a, b) *bridges* when a path of exposed edges (ridges' edges) joins a to b with
      every step shorter than |ab| / ratio: the front goes around the region the straight edge
      cuts across, through points that are themselves on the boundary. (graph_minimax)
    - A kept facet is dropped when one of its ridges is exposed with it as the only kept facet
      and has a bridging edge; repeated until none is. Dropping only adds exposed edges, and
      an edge that bridges keeps bridging as edges are added, so the result does not depend on
      the order of removal.

    The path must run along the boundary: where the front is two-dimensional, the points that
    join a and b lie inside it, the hull edge (a, b) is bridged by no boundary path, and the
    facets along the hull stay (a strip between two specialists and the nearest children is a
    gap to fill). Holes enclosed by kept facets are never exposed, so they stay gaps too.

    Loose edges: the edges of dropped facets that are no edge of a kept facet and whose ends no
    path of exposed edges joins in shorter steps (their length is their minimax distance: they
    are edges of the exposed edges' minimum spanning forest). Where the mesh was eroded down to
    a thin part of the front they are the steps between neighbouring points along it; a long
    edge of a dropped facet that the front goes around is not one. The shortest edge of the
    mesh is always either kept in a facet or loose, so facets and loose edges are never both
    empty. In canonical order (low, high), lexicographic.

    `ratio` None, no facet, or facets of 2 vertices (whose ridges are single points): every
    facet is kept, no loose edge. No fallback here: the mask may be all False.
    """
    f = np.asarray(facets, dtype=np.int64)
    keep = np.ones(len(f), dtype=bool)
    none = np.zeros((0, 2), dtype=np.int64)
    if ratio is None or len(f) == 0 or f.shape[1] < 3:
        return keep, none
    k = f.shape[1]
    p = np.asarray(points, dtype=float)
    all_edges = mesh_edges(f)
    # every length computed once, so that a step's length and its minimax distance are one float
    length = dict(zip(map(tuple, all_edges.tolist()), edge_lengths(p, all_edges).tolist()))
    owners: dict[tuple[int, ...], list[int]] = {}  # ridge -> the facets sharing it
    for i, row in enumerate(f.tolist()):
        for drop in range(k):
            owners.setdefault(tuple(row[:drop] + row[drop + 1 :]), []).append(i)
    live = {r: len(own) for r, own in owners.items()}  # kept facets sharing each ridge

    def pairs(ridge: tuple[int, ...]) -> list[tuple[int, int]]:
        return [(ridge[i], ridge[j]) for i in range(len(ridge)) for j in range(i + 1, len(ridge))]

    exposed = {e for r, n in live.items() if n < 2 for e in pairs(r)}
    while True:
        # Minimax distances along the exposed edges as they are now. Dropping facets below only
        # adds exposed edges, which can only shorten these distances, so an edge found to bridge
        # with them bridges still: facets can be dropped at once, and the distances are
        # recomputed when nothing more can be (the fixed point is reached when, freshly
        # computed, they make no boundary ridge bridge).
        graph = sorted(exposed)
        minimax = graph_minimax(p, np.array(graph, dtype=np.int64).reshape(-1, 2), [length[e] for e in graph])

        def bridging(ridge: tuple[int, ...]) -> bool:
            return any(length[(a, b)] > ratio * minimax[a, b] for a, b in pairs(ridge))

        queue = [r for r, n in live.items() if n == 1 and bridging(r)]
        if not queue:
            break
        while queue:
            ridge = queue.pop()
            if live[ridge] != 1:
                continue  # its last kept facet is already gone
            i = next(j for j in owners[ridge] if keep[j])
            keep[i] = False
            row = f[i].tolist()
            for drop in range(k):
                other = tuple(row[:drop] + row[drop + 1 :])
                live[other] -= 1
                exposed.update(pairs(other))
                if live[other] == 1 and bridging(other):
                    queue.append(other)
    covered = {tuple(e) for e in mesh_edges(f[keep]).tolist()}
    # a step between neighbours: no path of exposed edges joins its ends in shorter steps (its
    # length is their minimax distance: an edge of the exposed edges' minimum spanning forest)
    loose = [
        e
        for e in mesh_edges(f[~keep]).tolist()
        if tuple(e) not in covered and not length[tuple(e)] > minimax[e[0], e[1]]
    ]
    return keep, np.array(loose, dtype=np.int64).reshape(-1, 2)


def regular_simplex_volume(length: np.ndarray, d: int) -> np.ndarray:
    """The d-dimensional volume of the regular d-simplex with edges of `length`:
    length^d sqrt(d + 1) / (d! sqrt(2^d)). d = 1: the length itself; d = 2: sqrt(3) / 4 length^2
    (the equilateral triangle)."""
    return np.asarray(length, dtype=float) ** d * math.sqrt(d + 1) / (math.factorial(d) * math.sqrt(2.0**d))
