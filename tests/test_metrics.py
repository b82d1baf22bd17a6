"""pipeline.evaluation.metrics: hand-computed answers, a naive reference for expected utility, properties."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from pipeline.evaluation import metrics as M

# ---------------------------------------------------------------- known answers


def test_sparsity_pgmorl_hand_computed():
    # obj0 sorted 0,1,3 -> gaps 1,2; obj1 sorted 0,1,3 -> gaps 1,2; (1+4+1+4) / (3-1) = 5
    assert M.sparsity_pgmorl(np.array([[0, 3], [1, 1], [3, 0]])) == pytest.approx(5.0)


def test_sparsity_pgmorl_sorts_each_objective_separately():
    # Not a front: sorted by obj0 the obj1 values would be 5,0,4; sorted on their own: 0,4,5.
    p = np.array([[0.0, 5.0], [1.0, 0.0], [2.0, 4.0]])
    assert M.sparsity_pgmorl(p) == pytest.approx(((1 + 1) + (16 + 1)) / 2)


def test_sparsity_paper_hand_computed():
    # The paper's Table 1: mean Euclidean distance between neighbours along objective 0.
    # (0,3)-(1,1): sqrt(1+4) = 2.2361; (1,1)-(4,-3): sqrt(9+16) = 5; mean = 3.6180.
    # Given in shuffled order: the function sorts along objective 0 itself.
    p = np.array([[4.0, -3.0], [0.0, 3.0], [1.0, 1.0]])
    assert M.sparsity(p) == pytest.approx((math.sqrt(5) + 5) / 2)
    # PGMORL's on the same front: obj0 gaps 1,3; obj1 gaps (sorted -3,1,3) 4,2 -> (1+9+16+4)/2 = 15
    assert M.sparsity_pgmorl(p) == pytest.approx(15.0)


@pytest.mark.parametrize("fn", [M.sparsity, M.sparsity_pgmorl])
@pytest.mark.parametrize("pts", [np.zeros((0, 2)), np.array([[3.0, 4.0]])])
def test_sparsity_of_fewer_than_two_points_is_zero(pts, fn):
    assert fn(pts) == 0.0


def test_sparsity_of_duplicates_is_zero_and_counts_them():
    # Two identical points add a zero gap: (0 + 5) / 2 = 2.5 with the paper's definition.
    assert M.sparsity(np.array([[0.0, 0.0], [0.0, 0.0]])) == 0.0
    assert M.sparsity(np.array([[0.0, 4.0], [0.0, 4.0], [3.0, 0.0]])) == pytest.approx(2.5)
    # PGMORL's: obj0 sorted 0,0,3 -> gaps 0,3; obj1 sorted 0,4,4 -> gaps 4,0; (9 + 16) / (3 - 1) = 12.5
    assert M.sparsity_pgmorl(np.array([[0.0, 0.0], [0.0, 0.0]])) == 0.0
    assert M.sparsity_pgmorl(np.array([[0.0, 4.0], [0.0, 4.0], [3.0, 0.0]])) == pytest.approx(12.5)


def test_front_metrics_sparsity_counts_a_duplicate_point_once():
    # front_metrics scores the distinct non-dominated set: (0,4) twice is one point and (1,-0.5)
    # is dominated by (3,0), so the paper's sparsity is the single gap sqrt(9 + 16) = 5 and
    # PGMORL's (3^2 + 4^2) / (2 - 1) = 25
    m = M.front_metrics(np.array([[0.0, 4.0], [0.0, 4.0], [3.0, 0.0], [1.0, -0.5]]), [-1, -1], np.array([3.0, 4.0]))
    assert m["sparsity"] == pytest.approx(5.0) and m["sparsity_pgmorl"] == pytest.approx(25.0)
    assert m["cardinality"] == 2


def test_hypervolume_hand_computed():
    assert M.hypervolume(np.array([[2.0, 3.0]]), [0, 0]) == pytest.approx(6.0)
    # two boxes 1x3 and 3x1 overlapping in 1x1
    assert M.hypervolume(np.array([[1.0, 3.0], [3.0, 1.0]]), [0, 0]) == pytest.approx(5.0)
    # a point not strictly above the reference adds nothing
    assert M.hypervolume(np.array([[5.0, 0.0]]), [0, 0]) == 0.0
    assert M.hypervolume(np.zeros((0, 2)), [0, 0]) == 0.0


def test_hv_fraction_own_and_fixed_ideal():
    pts = np.array([[1.0, 3.0], [3.0, 1.0]])
    assert M.hv_fraction(pts, [0, 0]) == pytest.approx(5 / 9)
    assert M.hv_fraction(np.array([[2.0, 3.0]]), [0, 0]) == pytest.approx(1.0)
    assert M.hv_fraction(pts, [0, 0], ideal=np.array([6.0, 3.0])) == pytest.approx(5 / 18)
    assert M.hv_fraction(np.zeros((0, 2)), [0, 0]) == 0.0


def test_simplex_weights_two_objectives():
    w = M.simplex_weights(2, 5)
    assert w.shape == (5, 2)
    np.testing.assert_allclose(w[:, 0], [0, 0.25, 0.5, 0.75, 1])
    np.testing.assert_allclose(w.sum(axis=1), 1)


def test_simplex_weights_three_objectives_is_das_dennis_lattice():
    w = M.simplex_weights(3, 10)  # H = 3 gives C(5, 2) = 10 vectors
    assert w.shape == (10, 3)
    np.testing.assert_allclose(w.sum(axis=1), 1)
    np.testing.assert_allclose(w * 3, np.round(w * 3))
    assert len(np.unique(w, axis=0)) == 10
    assert len(M.simplex_weights(3, 11)) == 15  # H = 4


def test_expected_utility_hand_computed():
    pts = np.array([[10.0, 0.0], [0.0, 10.0]])
    assert M.expected_utility(pts, n_weights=2) == pytest.approx(10.0)
    # weights (0,1), (.5,.5), (1,0): max utilities 10, 5, 10
    assert M.expected_utility(pts, n_weights=3) == pytest.approx(25 / 3)
    with pytest.raises(ValueError):
        M.expected_utility(np.zeros((0, 2)))


def test_expected_utility_matches_naive_loop():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(17, 3)) * [100, 1, 10]
    w = M.simplex_weights(3, 50)
    naive = sum(max(float(np.dot(wi, p)) for p in pts) for wi in w) / len(w)
    assert M.expected_utility(pts, weights=w) == pytest.approx(naive)


def test_cardinality_counts_distinct_non_dominated():
    pts = np.array([[1.0, 3.0], [1.0, 3.0], [3.0, 1.0], [0.5, 0.5], [2.0, 2.0]])
    assert M.cardinality(pts) == 3  # the duplicate once, (0.5, 0.5) dominated


def test_distinct_count_merges_close_points():
    pts = np.array([[0.0, 1.0], [0.01, 0.99], [1.0, 0.0], [0.005, 0.5]])  # last: dominated by the 2nd
    lo, hi = np.zeros(2), np.ones(2)
    assert M.distinct_count(pts, lo, hi, tol=0.02) == 2  # first two are 0.014 apart
    assert M.distinct_count(pts, lo, hi, tol=0.01) == 3
    # normalisation: the same points on a 100x larger scale are still 0.014 of the range apart
    assert M.distinct_count(pts * 100, lo, hi * 100, tol=0.02) == 2
    assert M.distinct_count(np.array([[1.0, 1.0]] * 4), lo, hi) == 1
    assert M.distinct_count(np.zeros((0, 2)), lo, hi) == 0
    with pytest.raises(ValueError):
        M.distinct_count(pts, lo, hi, tol=0)


def test_distinct_count_zero_range_objective():
    pts = np.array([[0.0, 5.0], [1.0, 5.0 - 1e-12]])
    assert M.distinct_count(pts, np.array([0.0, 5.0]), np.array([1.0, 5.0])) == 2


def test_front_metrics_and_population_summary():
    pop = np.array([[0.0, 10.0], [10.0, 0.0], [6.0, 6.0], [1.0, 1.0], [-1.0, 2.0]])
    spec = np.array([True, True, False, False, False])
    s = M.population_summary(pop, spec, ref=[0.0, 0.0], tol=0.02, n_weights=3)
    assert s["ideal_point"] == [10.0, 10.0]
    # specialists sit on the axes: each is not strictly above the reference -> HV 0, ratio undefined
    assert s["specialists"]["hypervolume"] == 0.0 and s["hv_ratio_vs_specialists"] is None
    assert s["front"]["hypervolume"] == pytest.approx(36.0)
    assert s["front"]["cardinality"] == 3
    assert s["front"]["hv_fraction"] == pytest.approx(0.36)
    assert s["outside_reference"] == 3  # the two specialists and (-1, 2)

    s = M.population_summary(pop, spec, ref=[-1.0, -1.0])
    assert s["specialists"]["hypervolume"] == pytest.approx(11 + 11 - 1)
    # boxes 1x11, 11x1, 7x7 from (-1, -1): 11 + 11 + 49 - 1 - 7 - 7 + 1 (inclusion-exclusion)
    assert s["front"]["hypervolume"] == pytest.approx(57.0)
    assert s["hv_ratio_vs_specialists"] == pytest.approx(s["front"]["hypervolume"] / 21)


def test_hypervolume_history_hand_computed():
    # members: iteration 0: (4,1), (1,4); iteration 2: (3,3) then (2,2) (dominated); reference (0,0)
    it = np.array([0, 0, 2, 2])
    samples = np.array([10, 20, 30, 40])
    pts = np.array([[4.0, 1.0], [1.0, 4.0], [3.0, 3.0], [2.0, 2.0]])
    h = M.hypervolume_history(it, samples, {"a": pts, "b": pts[:, ::-1] * 2}, [0.0, 0.0])
    np.testing.assert_array_equal(h["iteration"], [0, 2])  # only the iterations present
    np.testing.assert_array_equal(h["population"], [2, 4])
    np.testing.assert_array_equal(h["env_samples"], [20, 40])
    # iteration 0: 4*1 + 1*4 - 1*1 = 7; iteration 2 adds (3,3): sweeping x downwards 4*1 + 3*2 + 1*1 = 11
    np.testing.assert_allclose(h["a"], [7.0, 11.0])
    np.testing.assert_allclose(h["b"], [28.0, 44.0])  # the same set mirrored and doubled: x4 the area
    with pytest.raises(ValueError):
        M.hypervolume_history(it, samples[:3], {"a": pts}, [0.0, 0.0])


def test_mean_sem():
    assert M.mean_sem([1.0, 2.0, 3.0]) == pytest.approx((2.0, 1 / math.sqrt(3)))
    m, s = M.mean_sem([4.0])
    assert m == 4.0 and math.isnan(s)


# ---------------------------------------------------------------- properties

coords = st.floats(-1e3, 1e3, allow_nan=False, width=32)
fronts = arrays(np.float64, st.tuples(st.integers(1, 12), st.just(2)), elements=coords)
REF = np.array([-1e3 - 1, -1e3 - 1])


@settings(max_examples=40, deadline=None)
@given(fronts, arrays(np.float64, (2,), elements=coords))
def test_hypervolume_monotone_when_adding_a_point(pts, extra):
    before = M.hypervolume(pts, REF)
    after = M.hypervolume(np.vstack([pts, extra]), REF)
    assert after >= before - 1e-9 * max(1.0, before)


@settings(max_examples=40, deadline=None)
@given(fronts)
def test_hv_fraction_in_unit_interval(pts):
    assert -1e-9 <= M.hv_fraction(pts, REF) <= 1 + 1e-9


@settings(max_examples=40, deadline=None)
@given(st.integers(2, 30), arrays(np.float64, (2,), elements=coords), arrays(np.float64, (2,), elements=coords))
def test_sparsity_of_evenly_spaced_segment(n, a, b):
    pts = a + np.linspace(0, 1, n)[:, None] * (b - a)
    expected = float(np.sum((b - a) ** 2)) / (n - 1) ** 2
    assert M.sparsity_pgmorl(pts) == pytest.approx(expected, rel=1e-6, abs=1e-6)
    assert M.sparsity(pts) == pytest.approx(math.sqrt(np.sum((b - a) ** 2)) / (n - 1), rel=1e-6, abs=1e-6)


@settings(max_examples=40, deadline=None)
@given(fronts, st.randoms(use_true_random=False), st.floats(0.001, 0.5))
def test_distinct_count_bounds_and_order_invariance(pts, rnd, tol):
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    k = M.distinct_count(pts, lo, hi, tol)
    assert 1 <= k <= M.cardinality(pts)
    perm = list(range(len(pts)))
    rnd.shuffle(perm)
    assert M.distinct_count(pts[perm], lo, hi, tol) == k


@settings(max_examples=40, deadline=None)
@given(fronts, arrays(np.float64, (2,), elements=coords))
def test_expected_utility_monotone_when_adding_a_point(pts, extra):
    assert M.expected_utility(np.vstack([pts, extra]), n_weights=11) >= M.expected_utility(pts, n_weights=11) - 1e-9


@settings(max_examples=40, deadline=None)
@given(fronts)
def test_non_dominated_is_idempotent_and_keeps_extremes(pts):
    nd = M.non_dominated(pts)
    np.testing.assert_array_equal(M.non_dominated(nd), nd)
    for j in range(2):  # a maximiser of one objective is never dominated unless tied
        assert nd[:, j].max() == pts[:, j].max()


@settings(max_examples=30, deadline=None)
@given(fronts, st.randoms(use_true_random=False))
def test_hypervolume_history_never_decreases_and_ends_at_the_whole_population(pts, rnd):
    it = np.array(sorted(rnd.randrange(0, 4) for _ in range(len(pts))))
    h = M.hypervolume_history(it, np.arange(len(pts)), {"hv": pts}, REF)
    assert np.all(np.diff(h["hv"]) >= -1e-9 * max(1.0, h["hv"].max()))
    assert h["hv"][-1] == pytest.approx(M.hypervolume(pts, REF)) and h["population"][-1] == len(pts)
