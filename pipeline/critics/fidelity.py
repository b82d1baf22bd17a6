"""Critic fidelity: how well Q^(k)_m(s, pi_k(s)) predicts the discounted return of objective m.

A diagnostic for the critic family of the paper's section "Secondary Critics" (used for both
jointly trained and post-hoc critics, the paper's joint-vs-post-hoc comparison). On the last
episodes of buffer D_k, each critic's prediction at the specialist's own action is compared
with the discounted Monte-Carlo return of the same objective computed from the stored rewards:

    G_m(s_t) = sum_{i >= t, same episode} gamma^(i - t) r_m(s_i, a_i)

Honest returns under truncation: a terminated episode's G is exact, so all its states are
used. An episode cut by the time limit (truncated) or by the end of training (neither flag
on its last row) lacks the tail gamma^(L - t + 1) V(s_{L+1}); the critics bootstrap through
such cuts, so only states whose missing tail weight is at most `tail_tolerance` are kept,
i.e. states with at least H = ceil(log(tail_tolerance) / log(gamma)) stored rows from s_t to
the cut (inclusive). The tail is dropped, not bootstrapped with the critic under test, so
G never borrows from the prediction it is compared with.

Caveat: the stored actions come from the behaviour policy (pi_k plus exploration noise,
and earlier versions of pi_k), so even an exact Q^{pi_k} differs somewhat from G. The
last episodes are used because they are closest to the final pi_k.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from typing import Any, Protocol, Sequence

import numpy as np
import torch

from pipeline.core.nets import Actor


class TwinCritic(Protocol):
    def twin_min(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor: ...  # (n_obj, B)


@dataclass(frozen=True)
class ObjectiveFidelity:
    """Agreement of one critic Q^(k)_m with the Monte-Carlo return G_m over the scored states.

    pearson:   Pearson correlation of Q and G over the states (None if either is constant
               or fewer than 2 states).
    rel_error: normalised error mean|Q - G| / mean|G| (None if mean|G| is 0 or no states):
               0 is perfect; a critic predicting half of every return scores 0.5.
    mean_q, mean_g: means of the prediction and of the return (None if no states); their
               ratio shows a scale bias (e.g. an under-trained critic at ~half the return).
    """

    objective: int
    n_states: int
    pearson: float | None
    rel_error: float | None
    mean_q: float | None
    mean_g: float | None


@dataclass(frozen=True)
class FidelityReport:
    gamma: float
    horizon: int  # H: rows needed before a cut for a state to be scored
    n_episodes: int  # episodes looked at (the last `episodes` of the buffer, or all if fewer)
    per_objective: list[ObjectiveFidelity]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: {"gamma", "horizon", "n_episodes", "obj<m>": {n_states, pearson, ...}}."""
        out: dict[str, Any] = {"gamma": self.gamma, "horizon": self.horizon, "n_episodes": self.n_episodes}
        for f in self.per_objective:
            d = asdict(f)
            out[f"obj{d.pop('objective')}"] = d
        return out


def tail_horizon(gamma: float, tail_tolerance: float) -> int:
    """Smallest H >= 1 with gamma^H <= tail_tolerance (1 if gamma is 0)."""
    if gamma <= 0.0:
        return 1
    return max(1, math.ceil(math.log(tail_tolerance) / math.log(gamma) - 1e-9))


def episode_runs(episode: np.ndarray) -> list[tuple[int, int]]:
    """Half-open row ranges [start, end) of the contiguous runs of equal `episode` (T,)."""
    if len(episode) == 0:
        return []
    cuts = np.flatnonzero(np.diff(episode) != 0) + 1
    bounds = np.concatenate([[0], cuts, [len(episode)]])
    return [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]


def discounted_returns(reward: np.ndarray, gamma: float) -> np.ndarray:
    """G_t = sum_{i >= t} gamma^(i-t) r_i within ONE episode segment: reward (L, M) -> (L, M) float64."""
    g = np.zeros(reward.shape, np.float64)
    acc = np.zeros(reward.shape[1:], np.float64)
    for t in range(len(reward) - 1, -1, -1):  # backward recursion; L is at most an episode
        acc = reward[t] + gamma * acc
        g[t] = acc
    return g


def scored_states(
    data: dict[str, np.ndarray], gamma: float, episodes: int, horizon: int
) -> tuple[np.ndarray, np.ndarray, int]:
    """Rows to score and their returns: (idx (S,) int64, G (S, n_objectives_env) float64, n_episodes).

    Takes the last `episodes` episode runs of the buffer. A run whose last row is terminated
    keeps every row; any other run (truncated, or still running when training stopped)
    keeps the rows with at least `horizon` rows from them to the run's end, inclusive.
    """
    runs = episode_runs(data["episode"])[-episodes:]
    idx, rets = [], []
    for start, end in runs:
        g = discounted_returns(data["reward"][start:end], gamma)
        keep = end - start if data["terminated"][end - 1] else max(0, end - start - horizon + 1)
        idx.append(np.arange(start, start + keep))
        rets.append(g[:keep])
    n_obj = data["reward"].shape[1]
    if not idx:
        return np.zeros(0, np.int64), np.zeros((0, n_obj)), 0
    return np.concatenate(idx), np.concatenate(rets), len(runs)


def _stats(objective: int, q: np.ndarray, g: np.ndarray) -> ObjectiveFidelity:
    n = len(q)
    if n == 0:
        return ObjectiveFidelity(objective, 0, None, None, None, None)
    pearson = None
    if n >= 2 and q.std() > 0 and g.std() > 0:
        pearson = float(np.corrcoef(q, g)[0, 1])
    scale = float(np.abs(g).mean())
    rel_error = float(np.abs(q - g).mean() / scale) if scale > 0 else None
    return ObjectiveFidelity(objective, n, pearson, rel_error, float(q.mean()), float(g.mean()))


@torch.no_grad()
def score_critics(
    data: dict[str, np.ndarray],
    critic: TwinCritic,
    objectives: Sequence[int],
    policy: Actor,
    gamma: float,
    episodes: int,
    tail_tolerance: float,
    chunk: int = 8192,
) -> FidelityReport:
    """Score each critic Q^(k)_m (m = objectives[j], min of its twin heads) against G_m.

    data: buffer D_k arrays (`load_buffer`); critic: an ensemble covering `objectives` in
    member order (its twin_min gives (len(objectives), B)); policy: pi_k, evaluated at the
    scored states; gamma: the discount the critic was trained with. Runs on the critic's
    device (critic and policy on the same one).
    """
    horizon = tail_horizon(gamma, tail_tolerance)
    idx, g, n_episodes = scored_states(data, gamma, episodes, horizon)
    params = getattr(critic, "parameters", None)
    device = next(params()).device if params is not None else torch.device("cpu")
    q = np.zeros((len(objectives), len(idx)), np.float64)
    for a in range(0, len(idx), chunk):
        obs = torch.from_numpy(data["obs"][idx[a : a + chunk]]).to(device)
        q[:, a : a + chunk] = critic.twin_min(obs, policy(obs)).double().cpu().numpy()
    per = [_stats(int(m), q[j], g[:, m]) for j, m in enumerate(objectives)]
    return FidelityReport(float(gamma), horizon, n_episodes, per)


def fidelity_json(report: FidelityReport, buffer_objective: int, **extra: Any) -> str:
    """Fidelity JSON text (DVC metrics); no NaN: undefined statistics are null."""
    return json.dumps({"buffer_objective": buffer_objective, **extra, **report.to_dict()}, indent=2) + "\n"


def mean_rel_error(report: FidelityReport) -> float:
    """The post-hoc fit's stopping rule: mean normalised error over the covered objectives (inf if undefined)."""
    errs = [f.rel_error for f in report.per_objective]
    return float(np.mean(errs)) if errs and all(e is not None for e in errs) else float("inf")
