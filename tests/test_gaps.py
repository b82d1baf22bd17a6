"""Gap identification for N >= 3 objectives (pipeline.core.front_mesh, pipeline.extraction.gaps),
N = 2 unchanged, and the paper's sparsity in N dimensions (docs/n_objectives.md).

Hand-checked sets: most are built so that their normalised points lie on a plane
x_0 + ... + x_{N-1} = const, where the projection onto the hyperplane orthogonal to (1, ..., 1)
is a mere translation, so distances and Delaunay circles can be worked out on paper.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from pipeline.core import front_mesh as fm
from pipeline.core.pareto import pareto_mask, population_scale
from pipeline.evaluation import metrics as M
from pipeline.extraction import gaps
from pipeline.extraction import mapex as ex

# ---------------------------------------------------------------- hand-checked sets

# FAN: A, B, C = the unit vectors, D = (0.6, 0.3, 0.2) inside their triangle once projected
# (its barycentric coordinates D - mean(D) + 1/3 = (0.567, 0.267, 0.167) are all positive),
# E dominated by D. Population range [0, 1] on every objective, so normalised = raw. The only
# triangulation of a triangle with one inner point is the fan: ABD, ACD, BCD, with areas
# |AB x AD| / 2 = |(0.2, 0.2, 0.1)| / 2 = 0.3 / 2, |AC x AD| / 2 = |(0.3, 0.2, 0.3)| / 2 =
# sqrt(0.22) / 2, |BC x BD| / 2 = |(0.5, 0.6, 0.6)| / 2 = sqrt(0.97) / 2.
FAN = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [0.6, 0.3, 0.2], [0.1, 0.1, 0.1]])
FAN_FACETS = [[0, 1, 3], [0, 2, 3], [1, 2, 3]]
FAN_AREAS = [0.15, math.sqrt(0.22) / 2, math.sqrt(0.97) / 2]

# RHOMBUS: P, Q, R, S with P - Q = (1, -1, 0) (length sqrt 2) and R - S = (-0.5, -0.5, 1)
# (length sqrt 1.5) perpendicular, crossing at their midpoints: a rhombus on the plane
# x + y + z = 1.5 (after normalisation: objective 2 spans [-0.5, 0.5], so it shifts by 0.5).
# Delaunay takes the shorter diagonal RS (the longer one, PQ, would put S inside the circle
# through P, Q, R): triangles PRS and QRS, each of area |RS| |PQ| / 4 = sqrt(3) / 4.
RHOMBUS = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.25, 0.25, 0.5], [0.75, 0.75, -0.5]])
RHOMBUS_FACETS = [[0, 2, 3], [1, 2, 3]]


def draw_shares(returns, facets, draws=3000, seed=0):
    """Empirical frequency of each facet (rows of `facets`) over `draws` calls of select_parents."""
    rng = np.random.default_rng(seed)
    got = [ex.select_parents(returns, rng) for _ in range(draws)]
    assert all(g in [tuple(f) for f in facets] for g in got)
    return np.array([np.mean([g == tuple(f) for g in got]) for f in facets])


def next_draw(rng: np.random.Generator) -> float:
    return float(rng.random())


# ---------------------------------------------------------------- the mesh


@pytest.mark.parametrize("m", [2, 3, 4, 6])
def test_diagonal_basis_is_orthonormal_and_orthogonal_to_the_diagonal(m):
    b = fm.diagonal_basis(m)
    assert b.shape == (m, m - 1)
    np.testing.assert_allclose(b.T @ b, np.eye(m - 1), atol=1e-12)
    np.testing.assert_allclose(np.ones(m) @ b, 0.0, atol=1e-12)


def test_projection_merges_exactly_the_points_that_differ_along_the_diagonal():
    rng = np.random.default_rng(0)
    for m in (3, 4, 5):
        a = rng.normal(size=m)
        assert np.allclose(fm.project([a, a + 2.5]), fm.project([a, a + 2.5])[0])  # a + c 1 dominates a
        # mutually non-dominated random points (on a sphere's negative orthant) project apart
        pts = -np.abs(rng.normal(size=(40, m)))
        pts /= np.linalg.norm(pts, axis=1, keepdims=True)
        assert pareto_mask(pts).all()
        y = fm.project(pts)
        dist = np.linalg.norm(y[:, None] - y[None], axis=-1)
        assert dist[~np.eye(len(y), dtype=bool)].min() > 1e-6


def test_two_objective_mesh_is_the_chain_along_objective_0():
    """For N = 2 the mesh rule gives the paper's edges: neighbours along objective 0."""
    rng = np.random.default_rng(1)
    for _ in range(50):
        t = np.sort(rng.uniform(0, 1, rng.integers(2, 12)))
        front = np.stack([t, 1 - t**2 + 0.1 * rng.normal(size=len(t))], axis=1)
        front = front[pareto_mask(front)]
        ids, lengths = gaps.front_edges(front)
        facets = fm.triangulate((front - population_scale(front)[0]) / population_scale(front)[1])
        chain = sorted(tuple(sorted(e)) for e in zip(ids[:-1].tolist(), ids[1:].tolist()))
        assert facets.tolist() == [list(e) for e in chain]
        sizes = fm.simplex_volumes((front - population_scale(front)[0]) / population_scale(front)[1], facets)
        np.testing.assert_allclose(sorted(sizes), sorted(lengths), rtol=1e-12)


def test_simplex_volumes_hand_cases():
    p = np.array([[0.0, 0, 0, 0], [3, 0, 0, 0], [0, 4, 0, 0], [0, 0, 5, 0], [1, 1, 1, 1]])
    # an edge of length 3, a right triangle of area 3 * 4 / 2, a tetrahedron of volume 3 * 4 * 5 / 6,
    # and a flat triangle (collinear vertices) of area 0
    assert fm.simplex_volumes(p, [[0, 1]]).tolist() == [3.0]
    np.testing.assert_allclose(fm.simplex_volumes(p, [[0, 1, 2]]), [6.0])
    np.testing.assert_allclose(fm.simplex_volumes(p, [[0, 1, 2, 3]]), [10.0])
    q = np.array([[0.0, 0, 0], [1, 1, 1], [2, 2, 2]])
    np.testing.assert_allclose(fm.simplex_volumes(q, [[0, 1, 2]]), [0.0], atol=1e-12)


# ---------------------------------------------------------------- N = 3: facets and roulette


def test_fan_facets_and_areas_by_hand_with_scaled_objectives():
    # raw objectives on wildly different scales and offsets: the normalised front is FAN's
    raw = FAN * np.array([1.0, 1000.0, 0.01]) + np.array([-50.0, 3.0, 7.0])
    facets, sizes = gaps.front_facets(raw)
    assert facets.tolist() == FAN_FACETS  # E (id 4, dominated) is in no facet
    np.testing.assert_allclose(sizes, FAN_AREAS, rtol=1e-12)


def test_roulette_frequencies_follow_facet_areas():
    p = np.array(FAN_AREAS) / sum(FAN_AREAS)  # 0.171, 0.267, 0.562
    shares = draw_shares(FAN, FAN_FACETS)
    np.testing.assert_allclose(shares, p, atol=0.035)  # ~4 standard deviations at 3000 draws


def test_delaunay_takes_the_short_diagonal_of_a_rhombus():
    facets, sizes = gaps.front_facets(RHOMBUS)
    assert facets.tolist() == RHOMBUS_FACETS
    np.testing.assert_allclose(sizes, [math.sqrt(3) / 4] * 2, rtol=1e-12)
    # one roulette draw per child, each of the two triangles half the time
    shares = draw_shares(RHOMBUS, RHOMBUS_FACETS, draws=2000, seed=3)
    np.testing.assert_allclose(shares, [0.5, 0.5], atol=0.045)


def test_parents_are_three_front_members_and_the_weight_is_unit():
    rng = np.random.default_rng(5)
    for _ in range(20):
        parents = ex.select_parents(FAN, rng)
        assert len(parents) == 3 and list(parents) == sorted(set(parents)) and 4 not in parents
        w = ex.target_weight(FAN, parents)
        assert w.shape == (3,) and np.linalg.norm(w) == pytest.approx(1.0) and (w >= 0).all()
        np.testing.assert_allclose(w, FAN[list(parents)].mean(axis=0) / np.linalg.norm(FAN[list(parents)].mean(axis=0)))


def test_one_draw_per_selection():
    """A selection consumes exactly one draw of the generator, as for N = 2."""
    a, b = np.random.default_rng(11), np.random.default_rng(11)
    ex.select_parents(FAN, a)
    b.random()
    assert next_draw(a) == next_draw(b)


# ---------------------------------------------------------------- degenerate fronts


def test_front_of_one_point_falls_back_to_the_per_objective_best_without_a_draw():
    returns = np.array([[5.0, 5.0, 5.0], [1.0, 4.0, 2.0], [4.0, 1.0, 3.0], [5.0, 0.0, 0.0]])
    facets, sizes = gaps.front_facets(returns)
    assert len(facets) == 0 and len(sizes) == 0
    rng, fresh = np.random.default_rng(2), np.random.default_rng(2)
    assert ex.select_parents(returns, rng) == (0, 0, 0)  # best on each: 0 (first on the tie with 3)
    assert next_draw(rng) == next_draw(fresh)
    # argmax over the whole population, lowest id on ties (as N = 2 always did): a dominated
    # policy that ties the front point on an objective is taken there
    returns = np.array([[5.0, 0.0, 1.0], [5.0, 5.0, 5.0], [0.0, 0.0, 5.0]])
    assert pareto_mask(returns).tolist() == [False, True, False]
    assert ex.select_parents(returns, np.random.default_rng(0)) == (0, 1, 1)


def test_all_equal_returns_give_the_lowest_ids_and_no_facet():
    returns = np.full((4, 3), 2.5)
    assert len(gaps.front_facets(returns)[0]) == 0
    rng, fresh = np.random.default_rng(9), np.random.default_rng(9)
    assert ex.select_parents(returns, rng) == (0, 0, 0)
    assert next_draw(rng) == next_draw(fresh)


def test_two_front_points_are_one_edge():
    returns = np.array([[0.0, 0.0, 0.0], [1.0, -1.0, 0.5], [-1.0, -2.0, -3.0]])  # 2 dominated by 0
    facets, sizes = gaps.front_facets(returns)
    assert facets.tolist() == [[0, 1]]
    span = np.array([2.0, 2.0, 3.5])  # population range per objective
    np.testing.assert_allclose(sizes, [np.linalg.norm(np.array([1.0, -1.0, 0.5]) / span)])
    assert ex.select_parents(returns, np.random.default_rng(0)) == (0, 1)


def test_three_collinear_points_are_two_edges_by_length():
    # on the line from (1, 0, 0) to (0, 1, 0): normalised edge lengths 0.7 sqrt 2 and 0.3 sqrt 2
    returns = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.3, 0.7, 0.0]])
    facets, sizes = gaps.front_facets(returns)
    assert facets.tolist() == [[0, 2], [1, 2]]
    np.testing.assert_allclose(sizes, [0.3 * math.sqrt(2), 0.7 * math.sqrt(2)], rtol=1e-12)
    np.testing.assert_allclose(draw_shares(returns, facets), [0.3, 0.7], atol=0.035)


def test_points_collinear_only_after_projection_are_edges_measured_in_3d():
    """p_i = a_i (1, -1, 0) + c_i (1, 1, 1): not collinear in 3-d, but their projections are (the
    mesh is a chain along a), and the edges' lengths are 3-d distances. A dominated point Z makes
    every objective's population range 10, so normalising is a uniform scale."""
    p0, p1, p2 = np.zeros(3), np.array([1.5, -0.5, 0.5]), np.array([1.7, -2.3, -0.3])  # a = 0, 1, 2
    z = np.array([1.7, 0.0, 0.5]) - 10.0
    returns = np.stack([p1, z, p2, p0])  # ids: p1 = 0, z = 1, p2 = 2, p0 = 3
    assert np.linalg.matrix_rank(np.stack([p1 - p0, p2 - p0])) == 2
    facets, sizes = gaps.front_facets(returns)
    assert facets.tolist() == [[0, 2], [0, 3]]  # p1-p2 and p0-p1: p0 and p2 are not neighbours
    np.testing.assert_allclose(sizes, [math.sqrt(3.92) / 10, math.sqrt(2.75) / 10], rtol=1e-12)


def test_four_objectives_coplanar_after_projection_give_triangles():
    """N = 4, front p0 = 0, p1 = a, p2 = b, p3 = a + b + 0.5 (1, 1, 1, 1) with a = (1, -1, 0, 0),
    b = (0, 1, 1, -2): affinely independent in 4-d, but their projections form a parallelogram
    (rank 2), triangulated along its shorter diagonal |a + b| = sqrt 6 (< |a - b| = sqrt 10):
    triangles p0 p1 p3 and p0 p2 p3, of 3 vertices each. Their areas are measured in 4-d:
    sqrt(|a|^2 |p3|^2 - (a.p3)^2) / 2 = sqrt(2 * 7 - 1) / 2 and sqrt(6 * 7 - 25) / 2, scaled by
    1 / 10^2 (the dominated point Z makes every range 10)."""
    a, b = np.array([1.0, -1.0, 0.0, 0.0]), np.array([0.0, 1.0, 1.0, -2.0])
    front = np.stack([np.zeros(4), a, b, a + b + 0.5])
    z = front.max(axis=0) - 10.0
    returns = np.vstack([front, z])
    assert pareto_mask(returns).tolist() == [True, True, True, True, False]
    assert np.linalg.matrix_rank(front[1:] - front[0]) == 3
    facets, sizes = gaps.front_facets(returns)
    assert facets.tolist() == [[0, 1, 3], [0, 2, 3]]
    np.testing.assert_allclose(sizes, [math.sqrt(13) / 200, math.sqrt(17) / 200], rtol=1e-9)
    parents = ex.select_parents(returns, np.random.default_rng(0))
    assert parents in [(0, 1, 3), (0, 2, 3)]
    assert ex.target_weight(returns, parents).shape == (4,)


def test_four_objectives_on_a_plane_in_4d_never_reach_qhull_flat(monkeypatch):
    """RHOMBUS with a constant 4th objective: the points span a plane in 4-d; full-rank
    Delaunay in 3-d would fail (qhull: flat input). Qhull is called once, on 2-d coordinates,
    and succeeds."""
    import scipy.spatial

    delaunay, shapes = scipy.spatial.Delaunay, []

    def spy(points, *args, **kwargs):
        shapes.append(np.shape(points))
        return delaunay(points, *args, **kwargs)

    monkeypatch.setattr(scipy.spatial, "Delaunay", spy)
    returns = np.hstack([RHOMBUS, np.full((4, 1), 3.0)])
    facets, sizes = gaps.front_facets(returns)
    assert shapes == [(4, 2)]
    assert facets.tolist() == RHOMBUS_FACETS
    np.testing.assert_allclose(sizes, [math.sqrt(3) / 4] * 2, rtol=1e-9)


def test_duplicates_keep_the_lowest_policy_id():
    # FAN with D first, and copies of A and D at higher ids: the mesh is FAN's, on the lowest ids
    order = [3, 0, 1, 2, 4]  # D, A, B, C, E
    returns = np.vstack([FAN[order], FAN[0], FAN[3]])  # ids 5 (= A) and 6 (= D) are copies
    facets, sizes = gaps.front_facets(returns)
    assert facets.tolist() == [[0, 1, 2], [0, 1, 3], [0, 2, 3]]  # D = 0, A = 1, B = 2, C = 3
    np.testing.assert_allclose(sorted(sizes), sorted(FAN_AREAS), rtol=1e-12)
    rng = np.random.default_rng(4)
    drawn = {p for _ in range(300) for p in ex.select_parents(returns, rng)}
    assert drawn == {0, 1, 2, 3}
    # on a line (no qhull): a copy of the middle point (id 3) is no vertex, not a zero-length edge
    line = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.3, 0.7, 0.0], [0.3, 0.7, 0.0]])
    assert gaps.front_facets(line)[0].tolist() == [[0, 2], [1, 2]]
    # and the copy first: the lowest id is kept
    assert gaps.front_facets(line[[3, 0, 1, 2]])[0].tolist() == [[0, 1], [0, 2]]


def test_distinct_points_closer_than_the_rank_tolerance_are_one_point():
    """Two front points 2e-14 apart in a population of range ~0.5: rank 0, no facet, the
    per-objective best as parents (policy 1 on objective 0, 0 on 1, 0 on the tie on 2)."""
    returns = np.array([[0.5, 0.5 + 2e-14, 0.5], [0.5 + 2e-14, 0.5, 0.5], [0.0, 0.0, 0.0]])
    assert pareto_mask(returns).tolist() == [True, True, False]
    assert len(gaps.front_facets(returns)[0]) == 0
    rng, fresh = np.random.default_rng(1), np.random.default_rng(1)
    assert ex.select_parents(returns, rng) == (1, 0, 0)
    assert next_draw(rng) == next_draw(fresh)


def test_facets_of_size_zero_fall_back_without_a_draw(monkeypatch):
    monkeypatch.setattr(gaps, "simplex_volumes", lambda points, facets: np.zeros(len(facets)))
    rng, fresh = np.random.default_rng(6), np.random.default_rng(6)
    assert ex.select_parents(FAN, rng) == (0, 1, 2)  # A, B, C: each best on its own objective
    assert next_draw(rng) == next_draw(fresh)


def test_a_qhull_error_drops_one_rank_instead_of_escaping(monkeypatch):
    import scipy.spatial
    from scipy.spatial import QhullError

    calls = []

    def flat(*args, **kwargs):
        calls.append(kwargs.get("qhull_options"))
        raise QhullError("QH6154 initial simplex is flat")

    monkeypatch.setattr(scipy.spatial, "Delaunay", flat)
    facets, sizes = gaps.front_facets(RHOMBUS)
    assert calls and "QJ" not in calls[0]
    assert facets.shape[1] == 2 and len(facets) == 3  # a chain through the 4 points
    assert (sizes > 0).all()


def test_near_degenerate_fronts_never_raise_and_give_front_parents():
    """Random small fronts in 3 to 5 objectives, many of them flat or nearly so (points on a
    random affine subspace plus noise from 0 to 1e-6): selection never raises, the parents are
    front members (rank + 1 of them, at most N) or the per-objective bests, and the target
    weight is a unit vector."""
    rng = np.random.default_rng(7)
    for trial in range(300):
        m = int(rng.integers(3, 6))
        n = int(rng.integers(1, 9))
        k = int(rng.integers(0, m))  # dimension of the affine subspace
        base = rng.normal(size=(k, m))
        pts = rng.normal(size=(n, k)) @ base + rng.normal(size=m)
        pts += rng.choice([0.0, 1e-15, 1e-9, 1e-6]) * rng.normal(size=pts.shape)
        if trial % 5 == 0:
            pts = np.vstack([pts, pts[: n // 2]])  # duplicates
        front = set(np.flatnonzero(pareto_mask(pts)).tolist())
        parents = ex.select_parents(pts, np.random.default_rng(trial))
        facets, sizes = gaps.front_facets(pts)
        if len(facets) and sizes.sum() > 0:
            assert set(parents) <= front and len(parents) == facets.shape[1] <= m
            assert list(parents) == sorted(set(parents))
        else:
            assert parents == gaps.best_per_objective(pts)
        assert np.linalg.norm(ex.target_weight(pts, parents)) == pytest.approx(1.0)
        # the same with the surface rule: front members, an edge or a facet, or the same fallback
        parents = ex.select_parents(pts, np.random.default_rng(trial), 3.0)
        if len(facets) and sizes.sum() > 0:
            assert set(parents) <= front and len(parents) in (2, facets.shape[1])
            assert list(parents) == sorted(set(parents))
        else:
            assert parents == gaps.best_per_objective(pts)
        assert np.linalg.norm(ex.target_weight(pts, parents)) == pytest.approx(1.0)


def test_one_objective_is_refused():
    with pytest.raises(ValueError, match="at least 2 objectives"):
        ex.select_parents(np.zeros((3, 1)), np.random.default_rng(0))


# ---------------------------------------------------------------- N = 2: bitwise as before


def reference_front_edges(returns):
    """front_edges as it was before N >= 3 (copied, frozen)."""
    if returns.shape[1] != 2:
        raise ValueError(f"gap identification is defined for 2 objectives (paper, Step 1), got {returns.shape[1]}")
    lo, span = population_scale(returns)
    ids = np.flatnonzero(pareto_mask(returns))
    ids = ids[np.lexsort((returns[ids, 1], returns[ids, 0]))]
    norm = (returns[ids] - lo) / span
    return ids, np.linalg.norm(np.diff(norm, axis=0), axis=1)


def reference_select_parents(returns, rng):
    """select_parents as it was before N >= 3 (copied, frozen)."""
    ids, lengths = reference_front_edges(returns)
    total = lengths.sum() if len(lengths) else 0.0
    if total <= 0:
        return int(np.argmax(returns[:, 0])), int(np.argmax(returns[:, 1]))
    e = int(rng.choice(len(lengths), p=lengths / total))
    return int(ids[e]), int(ids[e + 1])


def random_population(rng: np.random.Generator) -> np.ndarray:
    n = int(rng.integers(1, 14))
    kind = rng.integers(4)
    if kind == 0:  # continuous, different scales and signs
        return rng.normal(size=(n, 2)) * np.array([rng.uniform(0.1, 1e3), rng.uniform(0.1, 1e3)])
    if kind == 1:  # a small integer grid: ties and duplicates
        return rng.integers(0, 4, size=(n, 2)).astype(float)
    if kind == 2:  # all on one front
        t = rng.uniform(0, 1, n)
        return np.stack([t, 1 - t], axis=1) * np.array([100.0, -4500.0])
    return np.vstack([np.full((1, 2), 10.0), rng.uniform(0, 9, size=(n, 2))])  # one point dominates


def test_two_objectives_select_exactly_as_before_and_draw_the_same():
    rng = np.random.default_rng(2024)
    kinds = {"edge": 0, "fallback": 0}
    for trial in range(400):
        returns = random_population(rng)
        ids, lengths = ex.front_edges(returns)
        ref_ids, ref_lengths = reference_front_edges(returns)
        np.testing.assert_array_equal(ids, ref_ids)
        np.testing.assert_allclose(lengths, ref_lengths, rtol=1e-12, atol=0)  # two computations
        new, old = np.random.default_rng(trial), np.random.default_rng(trial)
        for _ in range(3):
            got, want = ex.select_parents(returns, new), reference_select_parents(returns, old)
            assert got == want and type(got) is tuple and all(type(i) is int for i in got)
        assert next_draw(new) == next_draw(old)
        kinds["edge" if len(lengths) and lengths.sum() > 0 else "fallback"] += 1
    assert kinds["edge"] > 50 and kinds["fallback"] > 20  # both branches were compared


# ---------------------------------------------------------------- sparsity in N dimensions


def reference_sparsity(points):
    """metrics.sparsity as it was before N >= 3 (copied, frozen)."""
    p = np.asarray(points, dtype=float)
    if len(p) < 2:
        return 0.0
    order = np.lexsort(p.T[::-1])
    return float(np.linalg.norm(np.diff(p[order], axis=0), axis=1).mean())


def test_two_objective_sparsity_is_what_it_was():
    rng = np.random.default_rng(8)
    for _ in range(200):
        pts = random_population(rng)
        assert M.sparsity(pts) == reference_sparsity(pts)
        front = M.non_dominated(pts)
        assert M.front_metrics(pts, [-1e4, -1e4], np.array([1e4, 1e4]))["sparsity"] == reference_sparsity(front)
        # and the mesh definition agrees on distinct fronts (the chain along objective 0)
        assert M.mesh_sparsity(front) == pytest.approx(reference_sparsity(front), rel=1e-12, abs=1e-12)


def test_three_objective_sparsity_uses_normalised_topology_and_raw_lengths():
    """RHOMBUS with objective 2 ten times larger. Scaled by its own ranges it is RHOMBUS, whose
    mesh has the short diagonal RS: edges PR, PS, QR, QS (each sqrt(0.75^2 + 0.25^2 + 5^2) raw)
    and RS (sqrt(0.5^2 + 0.5^2 + 10^2) raw). In raw units PQ would be the shorter diagonal."""
    raw = RHOMBUS * np.array([1.0, 1.0, 10.0])
    expected = (4 * math.sqrt(25.625) + math.sqrt(100.5)) / 5
    assert M.sparsity(raw) == pytest.approx(expected, rel=1e-12)
    with_pq = (4 * math.sqrt(25.625) + math.sqrt(2.0)) / 5
    assert abs(M.sparsity(raw) - with_pq) > 1.0
    assert M.front_metrics(raw, [-100.0] * 3, np.full(3, 100.0))["sparsity"] == pytest.approx(expected, rel=1e-12)


def test_three_objective_sparsity_of_the_fan():
    # edges AB, AC, BC (sqrt 2 each), AD, BD, CD; E is dominated and left out by front_metrics
    expected = (3 * math.sqrt(2) + math.sqrt(0.29) + math.sqrt(0.89) + math.sqrt(1.09)) / 6
    assert M.sparsity(FAN[:4]) == pytest.approx(expected, rel=1e-12)
    assert M.front_metrics(FAN, [-1.0] * 3, np.ones(3))["sparsity"] == pytest.approx(expected, rel=1e-12)


def test_four_objective_sparsity_of_coplanar_points():
    pts = np.hstack([RHOMBUS, np.full((4, 1), -7.0)])
    norm_rhombus = RHOMBUS + np.array([0.0, 0.0, 0.5])  # objective 2's range is already 1
    edges = [(0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    expected = np.mean([np.linalg.norm(norm_rhombus[i] - norm_rhombus[j]) for i, j in edges])
    assert M.sparsity(pts) == pytest.approx(expected, rel=1e-12)
    assert expected == pytest.approx((4 * math.sqrt(0.875) + math.sqrt(1.5)) / 5)


@pytest.mark.parametrize("n", [2, 3, 7])
def test_three_objective_sparsity_of_an_evenly_spaced_segment(n):
    a, b = np.array([0.0, 10.0, -3.0]), np.array([4.0, 2.0, 5.0])
    pts = a + np.linspace(0, 1, n)[:, None] * (b - a)
    assert M.sparsity(pts) == pytest.approx(np.linalg.norm(b - a) / (n - 1), rel=1e-12)


def test_three_objective_sparsity_degenerate_cases():
    assert M.sparsity(np.zeros((0, 3))) == 0.0
    assert M.sparsity(np.array([[1.0, 2.0, 3.0]])) == 0.0
    assert M.sparsity(np.full((5, 3), 4.0)) == 0.0  # all equal: one point
    two = np.array([[0.0, 1.0, 2.0], [3.0, -3.0, 2.0], [0.0, 1.0, 2.0]])  # a duplicate is merged
    assert M.sparsity(two) == pytest.approx(5.0)


# ---------------------------------------------------------------- end to end: mo-hopper-v5, 3 objectives


def test_extraction_with_three_objectives_end_to_end(tmp_path):
    """A tiny ExtractionRun on mo-hopper-v5 (obs 11, act 3, 3 objectives): the population's
    returns are set to FAN (so the front's mesh is the fan), then one iteration of one child (the
    CPU reference path) and one of two children (the stacked path). Each child has 3 parents,
    a facet of the front at the start of its iteration, and a unit 3-component weight; its
    returns have 3 components; the population saves and loads with them."""
    from pipeline.core.envs import make_env
    from pipeline.core.nets import Actor, CriticEnsemble
    from pipeline.core.population import load_population, save_population
    from pipeline.core.specialist import StartingPolicy
    from pipeline.extraction.run import ExtractionRun
    from pipeline.params.extract import ExtractParams

    obs_dim, act_dim, m = 11, 3, 3
    meta = {
        "env_id": "mo-hopper-v5",
        "obs_dim": obs_dim,
        "act_dim": act_dim,
        "n_objectives": m,
        "action_low": [-1.0] * act_dim,
        "action_high": [1.0] * act_dim,
    }
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        starts = [
            StartingPolicy(k % m, f"pop{k}", Actor(obs_dim, act_dim, [16], [-1.0] * 3, [1.0] * 3).eval(), [16])
            for k in range(5)
        ]
        critics = [CriticEnsemble(obs_dim, act_dim, [16], 2 * m).eval() for _ in range(m)]
    rng = np.random.default_rng(0)
    buffers = [
        {
            "obs": rng.normal(size=(300, obs_dim)).astype(np.float32),
            "action": rng.uniform(-1, 1, (300, act_dim)).astype(np.float32),
        }
        for _ in range(m)
    ]
    for k in (1, 2):
        cfg = ExtractParams(
            iterations=1,
            children_per_iteration=k,
            child_buffer_size=200,
            eval_episodes=1,
            warmup_steps=3,
            warmup_batch_size=32,
            epochs=1,
            beta=1.0,
            omega_max=20.0,
            batch_size=64,
            hidden_sizes=[16],
            device="cpu",
        )
        envs = [make_env("mo-hopper-v5", 15) for _ in range(k)]
        run = ExtractionRun(starts, buffers, critics, cfg, meta, seed=0, envs=envs, device=torch.device("cpu"))
        run.start()
        for member, returns in zip(run.members, FAN):
            member.returns = returns.tolist()
        run.step()
        children = run.members[5:]
        assert len(children) == k
        for child in children:
            assert tuple(child.parents) in [tuple(f) for f in FAN_FACETS]
            assert len(child.target_weight) == m
            assert np.linalg.norm(child.target_weight) == pytest.approx(1.0)
            assert len(child.returns) == m and np.isfinite(child.returns).all()
        save_population(tmp_path / f"population{k}.pt", run.members, meta)
        loaded, _ = load_population(tmp_path / f"population{k}.pt")
        assert [c.parents for c in loaded[5:]] == [c.parents for c in children]


# ---------------------------------------------------------------- N = 2 and the whole mesh: literal values from before

# Produced by the code of main at 6aca736 (before extract.facet_bridge_ratio existed), printed with
# repr: a 2-objective population (policy 8 dominated), its edges, their roulette probabilities and
# 16 draws from default_rng(31); and the 12-point ARC's facets, probabilities and 16 draws.
POP2 = np.array(
    [
        [1200.5, -3400.0],
        [2500.0, -4100.25],
        [300.0, -900.0],
        [1800.0, -3600.0],
        [900.0, -2500.0],
        [1000.0, -3000.0],
        [2100.0, -3900.0],
        [0.0, -350.0],
        [2100.0, -4000.0],
    ]
)
POP2_IDS = [7, 2, 4, 5, 0, 3, 6, 1]
POP2_P = [
    0.12547651763332263,
    0.3241358502388357,
    0.09217025778805933,
    0.08836425502465264,
    0.16266615355473715,
    0.09549665012783663,
    0.11169031563255605,
]
POP2_DRAWS = [(6, 1), (7, 2), (0, 3), (4, 5), (0, 3), (7, 2), (7, 2), (2, 4)]
POP2_DRAWS += [(6, 1), (2, 4), (5, 0), (6, 1), (0, 3), (2, 4), (2, 4), (7, 2)]
NEXT_DRAW_AFTER_16 = 0.2848570988390776  # one draw per selection, whatever the front

# ARC: 12 points on the curve (cos t, sin t, sin 2t), t evenly spaced over [0, pi / 2]: a thin
# (one-dimensional) curved front of 3 objectives, the example of issue 31. Its projection is
# convex, so the mesh fans across the region between the curve and the chord joining its ends.
_T = np.linspace(0, np.pi / 2, 12)
ARC = np.stack([np.cos(_T), np.sin(_T), np.sin(2 * _T)], axis=1)
ARC_FACETS = [[0, 1, 11], [1, 2, 9], [1, 9, 10], [1, 10, 11], [2, 3, 9], [3, 4, 7], [3, 7, 8], [3, 8, 9]]
ARC_FACETS += [[4, 5, 7], [5, 6, 7]]
ARC_P = [0.21481271861975307, 0.13253501765602343, 0.16572862606454844, 0.1820551975691523]
ARC_P += [0.10947483763400429, 0.03461378629348677, 0.05690617906296126, 0.0798280964188227]
ARC_P += [0.01800340539836579, 0.006042135282881986]
ARC_DRAWS = [(3, 8, 9), (0, 1, 11), (1, 10, 11), (1, 9, 10), (1, 10, 11), (0, 1, 11), (0, 1, 11), (0, 1, 11)]
ARC_DRAWS += [(4, 5, 7), (1, 2, 9), (1, 10, 11), (4, 5, 7), (2, 3, 9), (0, 1, 11), (1, 9, 10), (0, 1, 11)]


@pytest.mark.parametrize("ratio", [None, 3.0, 1.5])
def test_two_objectives_draw_the_literal_values_of_before_whatever_the_ratio(ratio):
    ids, lengths = ex.front_edges(POP2)
    assert ids.tolist() == POP2_IDS
    # main's values to the last bits this CPU's kernels may round differently (another CPU
    # generation may differ there); the draws below stay exact
    np.testing.assert_allclose(lengths / lengths.sum(), POP2_P, rtol=1e-12, atol=0)
    rng = np.random.default_rng(31)
    assert [gaps.select_parents(POP2, rng, ratio) for _ in range(16)] == POP2_DRAWS
    assert next_draw(rng) == NEXT_DRAW_AFTER_16


def test_without_a_ratio_the_arc_draws_the_literal_values_of_before():
    """The issue's numbers, reproduced: the facet joining both ends of the arc draws 21.5% of the
    probability, the one facet of consecutive points (5, 6, 7) 0.6%."""
    facets, sizes = gaps.front_facets(ARC)
    assert facets.tolist() == ARC_FACETS
    np.testing.assert_allclose(sizes / sizes.sum(), ARC_P, rtol=1e-12, atol=0)  # as for POP2_P
    found, found_sizes = gaps.front_gaps(ARC, None)
    assert found == [tuple(f) for f in ARC_FACETS] and found_sizes.tolist() == sizes.tolist()
    assert round(ARC_P[0], 3) == 0.215 and round(ARC_P[-1], 3) == 0.006
    rng = np.random.default_rng(31)
    assert [gaps.select_parents(ARC, rng) for _ in range(16)] == ARC_DRAWS
    assert next_draw(rng) == NEXT_DRAW_AFTER_16


# ---------------------------------------------------------------- gaps on the front's surface (facet_bridge_ratio)


def test_on_the_arc_the_spanning_facets_go_and_the_steps_between_neighbours_take_the_roulette():
    """Ratio 3 (the default): every facet joining points 5 or more steps apart along the arc is
    eroded (the chord 0-11 is bridged by the arc's own steps, each under a third of it, and so on
    inwards); 3 facets near the middle stay, and the 7 steps between neighbours they leave
    uncovered become 2-parent gaps sized as the equilateral triangle on them. The gaps between
    consecutive points (steps, and the facet 5-6-7) now draw 82.7% of the probability, against
    0.6% before, and the facet joining both ends nothing."""
    found, sizes = gaps.front_gaps(ARC, 3.0)
    facets, areas = gaps.front_facets(ARC)
    kept = [(3, 4, 7), (4, 5, 7), (5, 6, 7)]
    steps = [(0, 1), (1, 2), (2, 3), (7, 8), (8, 9), (9, 10), (10, 11)]
    assert found == kept + steps
    np.testing.assert_array_equal(sizes[:3], areas[[ARC_FACETS.index(list(f)) for f in kept]])
    lo, span = population_scale(ARC)
    norm = (ARC - lo) / span
    lengths = np.array([np.linalg.norm(norm[a] - norm[b]) for a, b in steps])
    np.testing.assert_allclose(sizes[3:], math.sqrt(3) / 4 * lengths**2, rtol=1e-12)
    p = sizes / sizes.sum()
    consecutive = sum(q for g, q in zip(found, p) if max(g) - min(g) == len(g) - 1)
    assert consecutive == pytest.approx(0.827, abs=5e-4)
    assert all(not {0, 11} <= set(g) for g in found)
    assert max(max(g) - min(g) for g in found) == 4
    # ratio 2: only the facet of 3 consecutive points stays, and every other step is a gap
    found2, sizes2 = gaps.front_gaps(ARC, 2.0)
    assert found2 == [(5, 6, 7)] + [(i, i + 1) for i in range(11) if i not in (5, 6)]
    # a larger ratio keeps more: at 5 no edge of this mesh bridges, nothing changes
    assert gaps.front_gaps(ARC, 5.0)[0] == [tuple(f) for f in ARC_FACETS]


def test_the_roulette_draws_the_surface_gaps_by_size_one_draw_each():
    found, sizes = gaps.front_gaps(ARC, 3.0)
    for seed in range(20):
        rng, ref = np.random.default_rng(seed), np.random.default_rng(seed)
        got = gaps.select_parents(ARC, rng, 3.0)
        assert got == found[int(ref.choice(len(sizes), p=sizes / sizes.sum()))]
        assert next_draw(rng) == next_draw(ref)
        w = ex.target_weight(ARC, got)
        assert w.shape == (3,) and np.linalg.norm(w) == pytest.approx(1.0)


def test_a_two_dimensional_front_with_its_specialists_at_the_corners_loses_nothing():
    """The three specialists at the corners and children inside (on the simplex, and on the
    sphere): the hull's edges are specialist to specialist, bridged by no path along the hull,
    so every facet stays, including the strips along the hull (2-objective trade-offs not yet
    explored). Were paths through the inside allowed, some of those strips would go."""
    rng = np.random.default_rng(1)
    dropped_by_inner_paths = 0
    for trial in range(40):
        n = int(rng.integers(3, 40))
        inner = rng.dirichlet(np.ones(3), size=n) if trial % 2 else np.abs(rng.normal(size=(n, 3)))
        if trial % 2 == 0:
            inner /= np.linalg.norm(inner, axis=1, keepdims=True)
        pop = np.vstack([np.eye(3), inner])
        facets, sizes = gaps.front_facets(pop)
        found, found_sizes = gaps.front_gaps(pop, 3.0)
        assert found == [tuple(f) for f in facets.tolist()]
        np.testing.assert_array_equal(found_sizes, sizes)
        # the same erosion with every mesh edge as a path would drop some strip facets
        lo, span = population_scale(pop)
        norm = (pop - lo) / span
        ids = np.flatnonzero(pareto_mask(pop))
        local = fm.triangulate(norm[ids])
        edges = fm.mesh_edges(local)
        minimax = fm.graph_minimax(norm[ids], edges)
        length = np.linalg.norm(norm[ids][edges[:, 0]] - norm[ids][edges[:, 1]], axis=1)
        dropped_by_inner_paths += int((length > 3.0 * minimax[edges[:, 0], edges[:, 1]]).any())
    assert dropped_by_inner_paths > 10  # the boundary rule is what keeps the strips


def test_a_hole_enclosed_by_the_front_stays_a_gap():
    """A jittered 7 x 7 grid on a plane orthogonal to (1, 1, 1) with its middle 3 x 3 left out:
    the facets across the hole have edges bridged through the grid (5 of them, via all mesh
    edges), but the hole is never reached from the hull, so every facet stays and the largest
    facet, in the hole, is still the most likely."""
    rng = np.random.default_rng(0)
    uv = np.array([(i, j) for i in range(7) for j in range(7) if not (2 <= i <= 4 and 2 <= j <= 4)], float) / 6
    uv += rng.uniform(-0.01, 0.01, uv.shape)
    pop = uv @ fm.diagonal_basis(3).T + 1.0
    assert pareto_mask(pop).all()
    facets, sizes = gaps.front_facets(pop)
    found, found_sizes = gaps.front_gaps(pop, 3.0)
    assert found == [tuple(f) for f in facets.tolist()]
    assert sizes.max() > 5 * np.median(sizes)  # the hole's facets are large
    lo, span = population_scale(pop)
    norm = (pop - lo) / span
    edges = fm.mesh_edges(fm.triangulate(norm))
    length = np.linalg.norm(norm[edges[:, 0]] - norm[edges[:, 1]], axis=1)
    assert (length > 3.0 * fm.graph_minimax(norm, edges)[edges[:, 0], edges[:, 1]]).sum() == 5


def test_surface_does_not_depend_on_the_order_of_the_points():
    """Relabelling the policies relabels the gaps and nothing else (thin, noisy and crescent
    fronts, where facets are dropped)."""
    rng = np.random.default_rng(4)
    checked = 0
    for trial in range(30):
        n = int(rng.integers(5, 30))
        t = np.sort(rng.uniform(0, np.pi / 2, n))
        radius = 1.0 if trial % 2 else rng.uniform(0.85, 1.0, n)
        pop = np.stack([radius * np.cos(t), radius * np.sin(t), rng.uniform(0.3, 1.0) * np.sin(2 * t)], axis=1)
        pop = pop[pareto_mask(pop)]
        found, sizes = gaps.front_gaps(pop, 3.0)
        perm = rng.permutation(len(pop))
        found_p, sizes_p = gaps.front_gaps(pop[perm], 3.0)
        relabelled = {tuple(sorted(int(perm[i]) for i in g)): s for g, s in zip(found_p, sizes_p)}
        assert relabelled.keys() == {g: 0 for g in found}.keys()
        np.testing.assert_allclose([relabelled[g] for g in found], sizes, rtol=1e-9)
        checked += len(found) < len(gaps.front_facets(pop)[0]) or any(len(g) == 2 for g in found)
    assert checked >= 5  # the rule changed the gaps of several of these fronts


def test_the_shortest_edge_never_bridges_so_the_rule_never_leaves_no_gap():
    rng = np.random.default_rng(2)
    for trial in range(100):
        m = 3 + trial % 2
        n = int(rng.integers(m + 1, 25))
        t = np.sort(rng.uniform(0, 1, n))
        pop = np.stack(
            [np.cos(t * np.pi / 2), np.sin(t * np.pi / 2)] + [rng.uniform(0, 1) * np.sin(np.pi * t)] * (m - 2), 1
        )
        pop = pop + rng.normal(scale=rng.choice([0.0, 1e-3, 3e-2]), size=pop.shape)
        found, sizes = gaps.front_gaps(pop, rng.uniform(1.01, 4.0))
        assert len(found) and sizes.sum() > 0 and (sizes >= 0).all()
        assert all(len(g) in (2, gaps.front_facets(pop)[0].shape[1]) for g in found)


def test_when_nothing_is_left_the_whole_mesh_is_used(monkeypatch):
    """A defensive fallback (the shortest edge keeps the rule from reaching it): with a surface
    of no facet and no edge, the gaps are the whole mesh."""
    monkeypatch.setattr(
        gaps, "surface", lambda points, facets, ratio: (np.zeros(len(facets), bool), np.zeros((0, 2), int))
    )
    found, sizes = gaps.front_gaps(ARC, 3.0)
    assert found == [tuple(f) for f in ARC_FACETS]
    np.testing.assert_allclose(sizes / sizes.sum(), ARC_P, rtol=1e-12)


def test_the_hand_checked_sets_are_unchanged_by_the_rule():
    for pop in (FAN, RHOMBUS, np.hstack([RHOMBUS, np.full((4, 1), 3.0)])):
        facets, sizes = gaps.front_facets(pop)
        found, found_sizes = gaps.front_gaps(pop, 3.0)
        assert found == [tuple(f) for f in facets.tolist()]
        np.testing.assert_array_equal(found_sizes, sizes)
    # collinear projections (a chain of edges): nothing to erode, whatever the ratio
    line = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.3, 0.7, 0.0]])
    assert gaps.front_gaps(line, 1.01)[0] == [(0, 2), (1, 2)]


def test_four_objectives_thin_curve_keeps_neighbours_only():
    """N = 4 (facets are tetrahedra, ridges triangles): 14 points evenly spaced (in normalised
    units) along a thin curve through 4-d. The mesh has tetrahedra joining both ends; with the
    rule every gap left joins points at most 4 steps apart (ratio 3) or is a step between
    neighbours (ratio 2), and the target weights are unit vectors of 4 components."""

    def curve(t):
        return np.stack([np.cos(t), np.sin(t), np.sin(2 * t), np.sin(2 * t) + 0.3 * np.sin(4 * t)], axis=1)

    dense = np.linspace(0, np.pi / 2, 20001)
    lo, span = population_scale(curve(dense))
    arc_length = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(curve(dense) / span, axis=0), axis=1))])
    pop = curve(np.interp(np.linspace(0, arc_length[-1], 14), arc_length, dense))
    assert pareto_mask(pop).all()
    facets, _ = gaps.front_facets(pop)
    assert facets.shape[1] == 4 and max(int(f.max() - f.min()) for f in facets) == 13
    found, sizes = gaps.front_gaps(pop, 3.0)
    assert max(max(g) - min(g) for g in found) == 4 and sizes.sum() > 0
    assert gaps.front_gaps(pop, 2.0)[0] == [(i, i + 1) for i in range(13)]
    parents = gaps.select_parents(pop, np.random.default_rng(0), 3.0)
    assert parents in found and np.linalg.norm(ex.target_weight(pop, parents)) == pytest.approx(1.0)


def test_graph_minimax_against_floyd_warshall():
    rng = np.random.default_rng(3)
    for _ in range(30):
        n = int(rng.integers(1, 12))
        pts = rng.normal(size=(n, 3))
        pairs = [(a, b) for a in range(n) for b in range(a + 1, n) if rng.random() < 0.4]
        edges = np.array(pairs, dtype=np.int64).reshape(-1, 2)
        ref = np.full((n, n), np.inf)
        np.fill_diagonal(ref, 0.0)
        for a, b in pairs:
            ref[a, b] = ref[b, a] = np.linalg.norm(pts[a] - pts[b])
        for k in range(n):  # minimax closure: the best path's longest step
            ref = np.minimum(ref, np.maximum(ref[:, [k]], ref[[k], :]))
        # the same distances summed in another order (the library's norms may go through BLAS,
        # whose kernel the CPU picks): equal to the last few bits, not bit for bit
        got = fm.graph_minimax(pts, edges)
        np.testing.assert_array_equal(np.isinf(got), np.isinf(ref))
        np.testing.assert_allclose(got, ref, rtol=1e-12, atol=0)


def test_regular_simplex_volume_by_hand():
    assert fm.regular_simplex_volume(np.array([2.5]), 1).tolist() == [2.5]  # N = 2 units: the length
    np.testing.assert_allclose(fm.regular_simplex_volume(np.array([2.0]), 2), [math.sqrt(3)])
    np.testing.assert_allclose(fm.regular_simplex_volume(np.array([3.0]), 3), [27 / (6 * math.sqrt(2))])
    # the equilateral triangle's area, as simplex_volumes measures it
    tri = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, math.sqrt(3) / 2, 0.0]])
    np.testing.assert_allclose(fm.simplex_volumes(tri, [[0, 1, 2]]), fm.regular_simplex_volume(np.array([1.0]), 2))


def test_the_stage_passes_the_ratio_to_the_roulette(monkeypatch):
    """extract.facet_bridge_ratio reaches select_parents through child_config and start_child;
    its default is 3 and it must exceed 1 (null allowed)."""
    from pipeline.extraction.run import child_config
    from pipeline.params.extract import ExtractParams

    assert ExtractParams().facet_bridge_ratio == 3.0
    assert ExtractParams(facet_bridge_ratio=None).facet_bridge_ratio is None
    with pytest.raises(ValueError, match="facet_bridge_ratio"):
        ExtractParams(facet_bridge_ratio=1.0)
    cfg = child_config(ExtractParams(facet_bridge_ratio=2.5, epochs=0, beta=1.0, omega_max=1.0))
    assert cfg.facet_bridge_ratio == 2.5
    seen = []

    def spy(returns, rng, ratio=None):
        seen.append(ratio)
        raise RuntimeError("stop after the parents")

    monkeypatch.setattr(ex, "select_parents", spy)
    with pytest.raises(RuntimeError, match="stop after the parents"):
        ex.start_child(ARC, [], [], cfg, np.random.default_rng(0), 0, "cpu")
    assert seen == [2.5]
