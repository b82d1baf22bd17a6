"""Pareto dominance, the non-dominated filter and hypervolume. Maximisation everywhere.

The one place that talks to pymoo (which minimises) is `hypervolume`: it flips signs once.
"""

from __future__ import annotations

import numpy as np


def pareto_mask(points: np.ndarray) -> np.ndarray:
    """Boolean mask (n,) of the non-dominated rows of `points` (n, m), maximising every column.

    A row is dominated if another row is >= in every objective and > in at least one (paper,
    "Pareto Dominance and Optimality"). Identical rows do not dominate each other: all are kept.
    """
    p = np.asarray(points, dtype=float)
    if p.ndim != 2:
        raise ValueError(f"points must be (n, m), got shape {p.shape}")
    ge = (p[:, None, :] >= p[None, :, :]).all(-1)  # ge[i, j]: i >= j everywhere
    gt = (p[:, None, :] > p[None, :, :]).any(-1)
    dominated_by = ge & gt  # [i, j]: i dominates j
    return ~dominated_by.any(axis=0)


def hypervolume(points: np.ndarray, ref: np.ndarray | list[float]) -> float:
    """Hypervolume dominated by `points` (n, m) and bounded below by the reference point `ref`.

    Points not strictly better than `ref` in every objective add nothing. Uses pymoo's exact
    algorithm on negated values (pymoo minimises).
    """
    from pymoo.indicators.hv import HV

    p = np.asarray(points, dtype=float).reshape(-1, len(ref))
    ref = np.asarray(ref, dtype=float)
    p = p[(p > ref).all(axis=1)]
    if len(p) == 0:
        return 0.0
    return float(HV(ref_point=-ref)(-p))


def ideal_box_volume(ideal: np.ndarray, ref: np.ndarray) -> float:
    """Volume of the box between the reference point and the ideal point (both (m,))."""
    return float(np.prod(np.clip(np.asarray(ideal, float) - np.asarray(ref, float), 0.0, None)))


def population_scale(returns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-objective (low, span) of the population's returns (n, m); a zero span becomes 1."""
    lo = returns.min(axis=0)
    span = returns.max(axis=0) - lo
    return lo, np.where(span > 0, span, 1.0)


def normalised_hypervolume(returns: np.ndarray) -> float:
    """Hypervolume of the returns scaled to [0, 1] by the population's own per-objective range,
    reference at 0: needs no reference point (shown while running; moves when the range does)."""
    lo, span = population_scale(returns)
    return hypervolume((returns - lo) / span, np.zeros(returns.shape[1]))
