"""NSGA-II tools on fitness vectors (maximisation): dominance, Pareto ranks, crowding distance,
the total preference order they give, survivor selection, tournament selection of crossover
parents and of single winners, and the update of an all-time archive of non-dominated points.
Generic: MOPDERL's phase 2 (pipeline/baselines/mopderl.py) uses them; its own rules (e.g.
`crossover_critic`) stay there."""

from __future__ import annotations

import numpy as np

from pipeline.core.pareto import pareto_mask


def dominance(points: np.ndarray) -> np.ndarray:
    """dom[i, j]: row i dominates row j (>= everywhere, > somewhere; maximisation)."""
    p = np.asarray(points, dtype=float)
    ge = (p[:, None, :] >= p[None, :, :]).all(-1)
    gt = (p[:, None, :] > p[None, :, :]).any(-1)
    return ge & gt


def nondominated_ranks(points: np.ndarray) -> np.ndarray:
    """Pareto rank of each row of `points` (n, m), maximising: 0 for the non-dominated rows,
    r for the rows non-dominated once ranks 0..r-1 are removed. Equal rows share a rank."""
    p = np.asarray(points, dtype=float)
    if p.ndim != 2:
        raise ValueError(f"points must be (n, m), got shape {p.shape}")
    dom = dominance(p)
    ranks = np.full(len(p), -1, dtype=np.int64)
    left = np.ones(len(p), dtype=bool)
    r = 0
    while left.any():
        # non-dominated among the rows left: no row left dominates it
        front = left & ~(dom & left[:, None]).any(axis=0)
        ranks[front] = r
        left &= ~front
        r += 1
    return ranks


def crowding_distance(points: np.ndarray) -> np.ndarray:
    """NSGA-II crowding distance of each row of one front `points` (n, m).

    Per objective, rows are sorted by value (ties by row index); the first and last get
    infinity, every other row adds (next - previous) / (max - min); an objective whose values
    are all equal adds nothing to the interior rows. Fronts of one or two rows: all infinite.
    """
    p = np.asarray(points, dtype=float)
    n, m = p.shape
    dist = np.zeros(n)
    if n <= 2:
        return np.full(n, np.inf)
    for j in range(m):
        order = np.argsort(p[:, j], kind="stable")
        values = p[order, j]
        span = values[-1] - values[0]
        dist[order[0]] = dist[order[-1]] = np.inf
        if span > 0:
            dist[order[1:-1]] += (values[2:] - values[:-2]) / span
    return dist


def nsga2_scores(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(Pareto rank, crowding distance within the row's own front) of each row of `points`."""
    ranks = nondominated_ranks(points)
    crowd = np.zeros(len(ranks))
    for r in np.unique(ranks):
        idx = np.flatnonzero(ranks == r)
        crowd[idx] = crowding_distance(np.asarray(points, dtype=float)[idx])
    return ranks, crowd


def preference_order(ranks: np.ndarray, crowding: np.ndarray) -> np.ndarray:
    """Row indices best first: lower rank, then larger crowding distance, then lower index."""
    n = len(ranks)
    return np.array(sorted(range(n), key=lambda i: (int(ranks[i]), -float(crowding[i]), i)), dtype=np.int64)


def preference_positions(ranks: np.ndarray, crowding: np.ndarray) -> np.ndarray:
    """Place of each row in `preference_order` (0 = best)."""
    order = preference_order(ranks, crowding)
    pos = np.empty(len(order), dtype=np.int64)
    pos[order] = np.arange(len(order))
    return pos


def nsga2_select(points: np.ndarray, n: int) -> list[int]:
    """NSGA-II survivor selection: the indices (ascending) of the `n` best rows of `points`.

    Whole fronts are taken in rank order while they fit; the front that does not fit is cut
    by decreasing crowding distance (ties: lower index). Fewer rows than `n`: all of them.
    """
    ranks, crowd = nsga2_scores(points)
    return sorted(int(i) for i in preference_order(ranks, crowd)[:n])


def tournament_pair(
    positions: np.ndarray, size: int, used: set[tuple[int, int]], rng: np.random.Generator
) -> tuple[int, int]:
    """Parents (better, worse) of one crossover, by tournament.

    Draws `size` entrants (with replacement) from the population, orders the distinct ones by
    `positions` (0 = best) and returns the first pair (in that order) of two distinct entrants
    not yet in `used`, which it then records. A draw with no such pair is redrawn; once every
    pair of the population is in `used`, it is emptied first. Needs >= 2 individuals.
    """
    n = len(positions)
    if n < 2:
        raise ValueError("a crossover tournament needs at least two individuals")
    if len(used) >= n * (n - 1) // 2:
        used.clear()
    while True:
        entrants = sorted({int(i) for i in rng.integers(0, n, size=size)}, key=lambda i: int(positions[i]))
        for a in range(len(entrants)):
            for b in range(a + 1, len(entrants)):
                key = (min(entrants[a], entrants[b]), max(entrants[a], entrants[b]))
                if key not in used:
                    used.add(key)
                    return entrants[a], entrants[b]


def tournament_winner(positions: np.ndarray, size: int, rng: np.random.Generator) -> int:
    """The best-placed of `size` entrants drawn with replacement."""
    entrants = rng.integers(0, len(positions), size=size)
    return int(min(entrants, key=lambda i: int(positions[i])))


def archive_update(archive_points: np.ndarray, new_points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Masks (keep, enter): archived rows that stay non-dominated, and new rows that join.

    The archive is the non-dominated set of everything ever evaluated: a new row joins unless
    an archived or another new row dominates it; an archived row leaves once a new row
    dominates it. Equal rows do not dominate each other (all are kept)."""
    a = np.asarray(archive_points, dtype=float).reshape(-1, np.shape(new_points)[1])
    mask = pareto_mask(np.concatenate([a, np.asarray(new_points, dtype=float)]))
    return mask[: len(a)], mask[len(a) :]
