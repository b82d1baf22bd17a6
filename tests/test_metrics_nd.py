"""The front metrics with 3 and 4 objectives, against references written here.

Hypervolume (pymoo behind `pipeline.core.pareto.hypervolume`) is compared with two exact
computations of the volume of a union of boxes that share nothing with pymoo: inclusion-exclusion
over subsets of points, and slicing along the last objective. The simplex weights are compared
with the Das-Dennis lattice listed by nested loops, expected utility with a plain double loop,
and cardinality, distinct_count and PGMORL sparsity with a small 3-objective front worked out
by hand.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from pipeline.core import pareto
from pipeline.evaluation import metrics as M

# ---------------------------------------------------------------- two exact references


def hv_inclusion_exclusion(points, ref) -> float:
    """Volume of the union of the boxes [ref, p]: sum over non-empty subsets S of the points of
    (-1)^(|S|+1) times the volume of their intersection, the box [ref, min over S]. Points not
    strictly above ref in every objective bound no volume and are dropped first."""
    ref = np.asarray(ref, float)
    pts = [np.asarray(p, float) for p in points if all(x > r for x, r in zip(p, ref))]
    total = 0.0
    for size in range(1, len(pts) + 1):
        for subset in itertools.combinations(pts, size):
            corner = np.min(subset, axis=0)
            total += (-1) ** (size + 1) * math.prod(corner - ref)
    return total


def hv_slicing(points, ref) -> float:
    """Volume of the union of the boxes [ref, p], one objective at a time: between two
    consecutive levels of the last objective the cross-section is the (m-1)-dimensional union
    of the boxes of the points reaching the upper level."""
    ref = np.asarray(ref, float)
    pts = np.asarray(points, float).reshape(-1, len(ref))
    pts = pts[(pts > ref).all(axis=1)]
    if len(pts) == 0:
        return 0.0
    if len(ref) == 1:
        return float(pts[:, 0].max() - ref[0])
    levels = np.concatenate([[ref[-1]], np.unique(pts[:, -1])])
    total = 0.0
    for lo, hi in zip(levels[:-1], levels[1:]):
        reaching = pts[pts[:, -1] >= hi, :-1]
        total += (hi - lo) * hv_slicing(reaching, ref[:-1])
    return total


def test_the_references_agree_on_hand_computed_volumes():
    # three 2 x 1 x 1 boxes, each pair and all three meeting in the unit cube: 6 - 3 + 1 = 4
    three = [[2, 1, 1], [1, 2, 1], [1, 1, 2]]
    assert hv_inclusion_exclusion(three, [0, 0, 0]) == hv_slicing(three, [0, 0, 0]) == 4.0
    assert hv_inclusion_exclusion([[3, 2, 4]], [1, 1, 1]) == hv_slicing([[3, 2, 4]], [1, 1, 1]) == 6.0
    # a box inside another adds nothing; a point on the reference plane bounds no volume
    assert hv_slicing([[2, 2, 2], [1, 1, 1], [5, 5, 0]], [0, 0, 0]) == 8.0
    assert hv_inclusion_exclusion([[2, 2, 2], [1, 1, 1], [5, 5, 0]], [0, 0, 0]) == 8.0


# ---------------------------------------------------------------- hypervolume


@pytest.mark.parametrize("hv", [pareto.hypervolume, M.hypervolume])
def test_hypervolume_three_objectives_by_hand(hv):
    ref = [0.0, 0.0, 0.0]
    assert hv(np.array([[2, 1, 1], [1, 2, 1], [1, 1, 2]], float), ref) == pytest.approx(4.0, abs=1e-12)
    # a dominated point, a duplicate and points on or below the reference change nothing
    more = np.array([[2, 1, 1], [1, 2, 1], [1, 1, 2], [1, 1, 1], [2, 1, 1], [5, 5, 0], [9, 9, -1]], float)
    assert hv(more, ref) == pytest.approx(4.0, abs=1e-12)
    # a shifted reference: the box [(1, 1, 1), (3, 2, 4)]
    assert hv(np.array([[3.0, 2.0, 4.0]]), [1.0, 1.0, 1.0]) == pytest.approx(6.0, abs=1e-12)
    # nothing strictly above the reference
    assert hv(np.array([[1.0, 5.0, 5.0], [5.0, 0.0, 5.0]]), [1.0, 0.0, 0.0]) == 0.0


def random_set(rng: np.random.Generator, m: int, n: int, ref: np.ndarray) -> np.ndarray:
    """n points on a coarse integer grid around ref (ties and dominated points are common), plus
    a duplicate, a point equal to ref in one objective and a point below ref in one."""
    pts = rng.integers(-2, 6, size=(n, m)).astype(float) + ref
    dup = pts[rng.integers(n)]
    on = pts[rng.integers(n)].copy()
    on[rng.integers(m)] = ref[0]
    below = np.full(m, 7.0) + ref
    below[rng.integers(m)] = ref[0] - 1.0
    return np.vstack([pts, dup, on, below])


@pytest.mark.parametrize("m", [3, 4])
@pytest.mark.parametrize("seed", range(12))
def test_hypervolume_matches_both_references_on_random_sets(m, seed):
    rng = np.random.default_rng(100 * m + seed)
    ref = np.full(m, float(rng.integers(-3, 3)))
    pts = random_set(rng, m, int(rng.integers(1, 9)), ref)
    want = hv_slicing(pts, ref)
    assert want == pytest.approx(hv_inclusion_exclusion(pts, ref), rel=1e-12, abs=1e-12)
    assert M.hypervolume(pts, ref) == pytest.approx(want, rel=1e-9, abs=1e-9)
    assert pareto.hypervolume(pts, ref) == pytest.approx(want, rel=1e-9, abs=1e-9)
    # the front alone has the same hypervolume, and the order of the points does not matter
    assert M.hypervolume(M.non_dominated(pts), ref) == pytest.approx(want, rel=1e-9, abs=1e-9)
    assert M.hypervolume(pts[rng.permutation(len(pts))], ref) == pytest.approx(want, rel=1e-9, abs=1e-9)


@pytest.mark.parametrize("m", [3, 4])
def test_hypervolume_of_continuous_points_with_a_mixed_reference(m):
    """Real-valued returns with a different reference value per objective (as an env's)."""
    rng = np.random.default_rng(m)
    ref = np.array([-100.0, -50.0, -3390.0, 0.0][:m])
    for _ in range(5):
        pts = ref + rng.uniform(-10, 1000, size=(25, m)) * np.array([3.0, 1.0, 2.0, 0.5][:m])
        assert M.hypervolume(pts, ref) == pytest.approx(hv_slicing(pts, ref), rel=1e-9)


# ---------------------------------------------------------------- weights and expected utility


def das_dennis(m: int, h: int) -> set[tuple[int, ...]]:
    """Every (c_1, ..., c_m) of non-negative integers summing to h, by nested loops."""
    if m == 1:
        return {(h,)}
    return {(c, *rest) for c in range(h + 1) for rest in das_dennis(m - 1, h - c)}


@pytest.mark.parametrize("m", [3, 4])
@pytest.mark.parametrize("n", [1, 3, 4, 10, 11, 50, 100])
def test_simplex_weights_are_the_smallest_das_dennis_lattice_with_n_rows(m, n):
    w = M.simplex_weights(m, n)
    assert w.shape[1] == m and (w >= 0).all()
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=0, atol=1e-12)
    # H divisions: the fewest with at least n points
    h = next(h for h in itertools.count(1) if len(das_dennis(m, h)) >= n)
    assert len(w) == len(das_dennis(m, h)) >= n
    assert h == 1 or len(das_dennis(m, h - 1)) < n
    got = {tuple(int(round(x)) for x in row * h) for row in w}
    np.testing.assert_allclose(w * h, np.round(w * h), atol=1e-9)  # on the lattice
    assert got == das_dennis(m, h) and len(got) == len(w)  # all of it, once each
    # evenly spread: every weight's nearest other weight is one lattice step (sqrt 2 / H) away
    d = np.linalg.norm(w[:, None] - w[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    np.testing.assert_allclose(d.min(axis=1), math.sqrt(2) / h, rtol=1e-12)


def brute_force_utility(points: np.ndarray, weights) -> float:
    total = 0.0
    for w in weights:
        total += max(sum(wk * pk for wk, pk in zip(w, p)) for p in points)
    return total / len(weights)


@pytest.mark.parametrize("n_weights", [3, 10, 100])
@pytest.mark.parametrize("seed", range(4))
def test_expected_utility_three_objectives_is_the_mean_of_the_best_weighted_sum(seed, n_weights):
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(int(rng.integers(1, 15)), 3)) * np.array([1000.0, 50.0, 300.0])
    h = next(h for h in itertools.count(1) if len(das_dennis(3, h)) >= n_weights)
    lattice = [np.array(c) / h for c in sorted(das_dennis(3, h))]
    assert M.expected_utility(pts, n_weights=n_weights) == pytest.approx(brute_force_utility(pts, lattice), rel=1e-12)


def test_expected_utility_three_objectives_by_hand():
    front = np.array([[0.0, 0.0, 3.0], [1.0, 1.0, 1.0], [3.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    w = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1 / 3, 1 / 3, 1 / 3]])
    # best per weight: 3, 2, 3 and 1 (three points tie at sum 3)
    assert M.expected_utility(front, weights=w) == pytest.approx((3 + 2 + 3 + 1) / 4)
    with pytest.raises(ValueError, match="weights must be"):
        M.expected_utility(front, weights=w[:, :2])


# ---------------------------------------------------------------- counts and spacing of a small front

# (0, 0, 3), (1, 1, 1), (3, 0, 0) and (0, 2, 0) are non-dominated; (1, 1, 1) comes twice and
# (0.5, 0.5, 0.5) is dominated by it.
SMALL = np.array([[0, 0, 3], [1, 1, 1], [3, 0, 0], [1, 1, 1], [0.5, 0.5, 0.5], [0, 2, 0]], float)


def test_cardinality_and_non_dominated_of_a_small_front():
    assert M.cardinality(SMALL) == 4
    np.testing.assert_array_equal(M.non_dominated(SMALL), [[0, 0, 3], [0, 2, 0], [1, 1, 1], [3, 0, 0]])
    np.testing.assert_array_equal(pareto.pareto_mask(SMALL), [True, True, True, True, False, True])


@pytest.mark.parametrize(("tol", "expected"), [(0.5, 4), (0.6, 3), (1.3, 2), (2.0, 1)])
def test_distinct_count_of_a_small_front_by_hand(tol, expected):
    """On the box [0, 3]^3 the front is (0, 0, 1), (0, 2/3, 0), (1/3, 1/3, 1/3), (1, 0, 0) in that
    (lexicographic) order. Distances: (1/3, 1/3, 1/3) is 0.577 from (0, 2/3, 0) and 0.816 from
    (0, 0, 1); (0, 2/3, 0) is 1.20 from (0, 0, 1) and from (1, 0, 0); (1, 0, 0) is 1.41 from (0, 0, 1)."""
    assert M.distinct_count(SMALL, np.zeros(3), np.full(3, 3.0), tol) == expected


def test_sparsity_pgmorl_of_a_small_front_by_hand():
    """Sorted per objective: x 0, 0, 1, 3 (squared gaps 0 + 1 + 4), y 0, 0, 1, 2 (0 + 1 + 1),
    z 0, 0, 1, 3 (0 + 1 + 4): 12 over n - 1 = 3."""
    front = M.non_dominated(SMALL)
    assert M.sparsity_pgmorl(front) == pytest.approx(4.0)
    assert M.front_metrics(SMALL, [-1, -1, -1], [3, 2, 3])["sparsity_pgmorl"] == pytest.approx(4.0)


def test_front_metrics_three_objectives():
    ref, ideal = np.array([-1.0, -1.0, -1.0]), np.array([3.0, 2.0, 3.0])
    got = M.front_metrics(SMALL, ref, ideal, tol=0.6, n_weights=10)
    front = M.non_dominated(SMALL)
    assert got["cardinality"] == 4
    assert got["hypervolume"] == pytest.approx(hv_slicing(front, ref))
    assert got["hv_fraction"] == pytest.approx(hv_slicing(front, ref) / (4 * 3 * 4))
    # distinct_count normalises by the [ref, ideal] box: (1, 1, 1) and (0, 2, 0) are 0.49 apart there
    assert got["distinct_count"] == M.distinct_count(front, ref, ideal, 0.6) == 3
    lattice = [np.array(c) / 3 for c in das_dennis(3, 3)]
    assert got["expected_utility"] == pytest.approx(brute_force_utility(front, lattice))
