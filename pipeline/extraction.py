"""MAPEX extraction (paper, Algorithm 1 and section "Method", steps 1-3).

Each iteration: find the non-dominated set of the population, pick a gap on it by roulette
wheel over edge lengths, derive the target weight from the parents' centroid, build a hybrid
buffer from the specialists' buffers in proportion to the weight, warm a fresh policy up on
the mean parent action, then train it by mixed-advantage-weighted regression.

Deviations from the paper, each a param unless it is a necessary reading:
- Edge lengths and the centroid are measured in objective space normalised by the population's
  per-objective range (necessary: raw returns differ in scale by orders of magnitude and can be
  negative, so a raw centroid can point anywhere, even away from both parents).
- `advantage_norm`: the paper mixes raw advantages; `zscore` (the precursor code) and
  `objective_range` (each A_m divided by objective m's population range, the same units as w)
  are options.
- `advantage_recompute: once` computes Q(s, pi_new(s)) once after warm-up (precursor code)
  instead of at every step (Algorithm 1).
An advantage always weights exactly the row it was computed for (the precursor code paired
them with resampled rows, a bug not reproduced here).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import torch

from pipeline.nets import Actor, CriticEnsemble
from pipeline.pareto import pareto_mask


# ---------------------------------------------------------------- step 1: gaps and weights


def population_scale(returns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-objective (low, span) of the population's returns (n, m); a zero span becomes 1."""
    lo = returns.min(axis=0)
    span = returns.max(axis=0) - lo
    return lo, np.where(span > 0, span, 1.0)


def front_edges(returns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Non-dominated policies sorted along objective 0, and the normalised lengths of the edges
    between sorted neighbours.

    returns: (n, 2). Result: ids (f,) and lengths (f - 1,), Euclidean in objective space scaled
    by the population's per-objective range.
    """
    if returns.shape[1] != 2:
        raise ValueError(
            f"gap identification is defined for 2 objectives (paper, Step 1), got {returns.shape[1]}"
        )
    lo, span = population_scale(returns)
    ids = np.flatnonzero(pareto_mask(returns))
    # Ties on objective 0 are broken by objective 1 so the order is total and reproducible.
    ids = ids[np.lexsort((returns[ids, 1], returns[ids, 0]))]
    norm = (returns[ids] - lo) / span
    return ids, np.linalg.norm(np.diff(norm, axis=0), axis=1)


def select_parents(returns: np.ndarray, rng: np.random.Generator) -> tuple[int, int]:
    """Draw one front edge with probability proportional to its normalised length (roulette
    wheel, paper Step 1) and return its two endpoint policy ids.

    If the front has no edge of positive length (one policy dominates all others), the two
    policies that are best on each objective are used as parents.
    """
    ids, lengths = front_edges(returns)
    total = lengths.sum() if len(lengths) else 0.0
    if total <= 0:
        return int(np.argmax(returns[:, 0])), int(np.argmax(returns[:, 1]))
    e = int(rng.choice(len(lengths), p=lengths / total))
    return int(ids[e]), int(ids[e + 1])


def target_weight(returns: np.ndarray, parents: Sequence[int], norm: str = "l2") -> np.ndarray:
    """Unit target weight towards the centroid of the parents' normalised returns (paper Step 1).

    Returns are scaled to [0, 1] by the population's per-objective range before the centroid is
    taken; the centroid is divided by its L2 norm (paper) or L1 sum (precursor). A zero centroid
    gives the uniform weight.
    """
    lo, span = population_scale(returns)
    centroid = ((returns[list(parents)] - lo) / span).mean(axis=0)
    size = np.linalg.norm(centroid) if norm == "l2" else np.abs(centroid).sum()
    if size <= 1e-12:
        m = returns.shape[1]
        return np.full(m, 1 / np.sqrt(m) if norm == "l2" else 1 / m)
    return centroid / size


# ---------------------------------------------------------------- step 2: hybrid buffer


@dataclass
class Hybrid:
    """A child's training set: rows drawn from the specialists' buffers."""

    obs: torch.Tensor  # (N, obs_dim)
    action: torch.Tensor  # (N, act_dim)
    origin: torch.Tensor  # (N,) int64: k of the buffer D_k each row came from
    index: np.ndarray  # (N,) row index inside its origin buffer


def hybrid_counts(weight: np.ndarray, size: int, buffer_sizes: Sequence[int]) -> np.ndarray:
    """Rows to draw from each buffer, in proportion w_k / sum(w) (paper Step 2).

    If a buffer holds fewer rows than its share of `size`, the whole hybrid buffer shrinks so
    the proportions still hold (capping one count alone would skew them towards the other
    buffers). Counts are rounded independently, so the total can differ from the target by one.
    """
    share = np.clip(weight, 0, None)
    share = share / share.sum() if share.sum() > 0 else np.full(len(weight), 1 / len(weight))
    sizes = np.asarray(buffer_sizes, dtype=np.float64)
    with np.errstate(divide="ignore", over="ignore"):
        fits = np.where(share > 0, sizes / share, np.inf)
    total = min(float(size), float(fits.min()))
    counts = np.floor(share * total + 0.5).astype(np.int64)
    return np.minimum(counts, sizes.astype(np.int64))


def build_hybrid(
    buffers: Sequence[dict[str, np.ndarray]], weight: np.ndarray, size: int, rng: np.random.Generator, device
) -> Hybrid:
    """Draw rows without replacement inside each buffer, in proportion to the target weight."""
    counts = hybrid_counts(weight, size, [len(b["obs"]) for b in buffers])
    obs, act, origin, index = [], [], [], []
    for k, (buf, n) in enumerate(zip(buffers, counts)):
        idx = np.sort(rng.choice(len(buf["obs"]), size=int(n), replace=False))
        obs.append(buf["obs"][idx])
        act.append(buf["action"][idx])
        origin.append(np.full(len(idx), k, dtype=np.int64))
        index.append(idx)
    return Hybrid(
        obs=torch.from_numpy(np.concatenate(obs)).to(device),
        action=torch.from_numpy(np.concatenate(act)).to(device),
        origin=torch.from_numpy(np.concatenate(origin)).to(device),
        index=np.concatenate(index),
    )


# ---------------------------------------------------------------- warm-up


@torch.no_grad()
def mean_parent_action(parents: Sequence[Actor], obs: torch.Tensor, chunk: int = 65_536) -> torch.Tensor:
    """a_bar(s) = mean over parents of pi_p(s), for every row of obs (N, obs_dim) -> (N, act_dim)."""
    out = []
    for i in range(0, len(obs), chunk):
        o = obs[i : i + chunk]
        out.append(torch.stack([p(o) for p in parents]).mean(dim=0))
    return torch.cat(out)


def regression_step(actor: Actor, opt: torch.optim.Optimizer, obs, target, weight=None, max_grad_norm=None, pred=None) -> torch.Tensor:
    """One Adam step on mean_b weight_b * ||pi(s_b) - target_b||^2 (weight None = 1).

    `pred` = actor(obs) if the caller already computed it (with grad), to avoid a second pass.
    """
    pred = actor(obs) if pred is None else pred
    sq = ((pred - target) ** 2).sum(dim=-1)
    loss = (sq * weight).mean() if weight is not None else sq.mean()
    opt.zero_grad(set_to_none=True)
    loss.backward()
    if max_grad_norm is not None:
        torch.nn.utils.clip_grad_norm_(actor.parameters(), max_grad_norm)
    opt.step()
    return loss.detach()


def warm_up(actor: Actor, obs: torch.Tensor, target: torch.Tensor, steps: int, lr: float, batch_size: int, rng: np.random.Generator) -> None:
    """Regress `actor` onto `target` actions at hybrid states (paper eq. L_init), `steps` steps."""
    opt = torch.optim.Adam(actor.parameters(), lr=lr)
    n = len(obs)
    for _ in range(steps):
        idx = torch.from_numpy(rng.integers(0, n, size=min(batch_size, n))).to(obs.device)
        regression_step(actor, opt, obs[idx], target[idx])


# ---------------------------------------------------------------- step 2-3: mixed advantage


@torch.no_grad()
def critic_values(
    critics: Sequence[CriticEnsemble], obs: torch.Tensor, action: torch.Tensor, origin: torch.Tensor, chunk: int = 65_536
) -> torch.Tensor:
    """Q^(k)_m(s, a) for each row with k = the row's origin: (B, m), min over the twin heads.

    Each row is evaluated only by the critics trained on the buffer it came from
    (paper, "Secondary Critics"). Rows are processed `chunk` at a time to bound memory.
    """
    if len(obs) > chunk:
        return torch.cat([critic_values(critics, obs[i : i + chunk], action[i : i + chunk], origin[i : i + chunk], chunk)
                          for i in range(0, len(obs), chunk)])
    if obs.is_cuda:
        # On a GPU, evaluating every critic on every row and selecting costs little, while
        # indexing by a boolean mask would make the host wait for the device at every step.
        every = torch.stack([c.twin_min(obs, action).T for c in critics])  # (K, B, m)
        return every.gather(0, origin.view(1, -1, 1).expand(1, -1, every.shape[2])).squeeze(0)
    m = critics[0].n_members // 2
    out = torch.empty(len(obs), m, device=obs.device)
    for k, critic in enumerate(critics):
        rows = (origin == k).nonzero(as_tuple=True)[0]
        if len(rows):
            out[rows] = critic.twin_min(obs[rows], action[rows]).T
    return out


def mixed_advantage(q_sa: torch.Tensor, q_pi: torch.Tensor, weight: torch.Tensor, norm: str, scale: torch.Tensor | None = None) -> torch.Tensor:
    """A_mixed = w . (Q(s, a) - Q(s, pi_new(s))) per row (paper eqs. "mixed advantage").

    q_sa, q_pi: (B, m); weight: (m,); scale: (m,) objective ranges for norm="objective_range".
    norm="zscore" standardises A_mixed over the rows given: the whole hybrid buffer when
    Q(s, pi_new(s)) is computed once (the precursor code), each minibatch when recomputed.
    """
    adv = q_sa - q_pi
    if norm == "objective_range":
        adv = adv / scale
    mixed = adv @ weight
    if norm == "zscore":
        mixed = (mixed - mixed.mean()) / (mixed.std(unbiased=False) + 1e-8)
    return mixed


def awr_weight(mixed: torch.Tensor, beta: float, omega_max: float) -> torch.Tensor:
    """omega = min(exp(A_mixed / beta), omega_max) (paper Step 3), computed without overflow."""
    return torch.exp(torch.clamp(mixed / beta, max=float(np.log(omega_max))))


@dataclass(frozen=True)
class AdvantageConfig:
    epochs: int
    beta: float
    omega_max: float
    lr: float
    batch_size: int
    max_grad_norm: float | None
    recompute: str  # "every_step" | "once"
    norm: str  # "none" | "zscore" | "objective_range"


def advantage_weighted_regression(
    actor: Actor,
    hybrid: Hybrid,
    critics: Sequence[CriticEnsemble],
    weight: torch.Tensor,
    scale: torch.Tensor,
    cfg: AdvantageConfig,
    rng: np.random.Generator,
    on_step: Callable[[], None] | None = None,
) -> dict[str, float]:
    """Train `actor` for cfg.epochs shuffled passes over the hybrid buffer (paper Step 3).

    Row b of a minibatch is weighted by omega computed from that same row's (s, a): the
    minibatch indices are drawn once and used for Q(s, a), Q(s, pi_new(s)) and the loss alike.
    Returns summary statistics of the weights (mean, fraction clipped at omega_max).
    """
    n = len(hybrid.obs)
    if cfg.epochs == 0 or n == 0:
        return {"omega_mean": float("nan"), "omega_clipped": float("nan")}
    opt = torch.optim.Adam(actor.parameters(), lr=cfg.lr)
    q_sa_all = critic_values(critics, hybrid.obs, hybrid.action, hybrid.origin)
    fixed = None
    if cfg.recompute == "once":
        with torch.no_grad():
            # pi_new(s) for every row, chunked and without grad (a "mean" over one policy)
            q_pi_all = critic_values(critics, hybrid.obs, mean_parent_action([actor], hybrid.obs), hybrid.origin)
        fixed = awr_weight(mixed_advantage(q_sa_all, q_pi_all, weight, cfg.norm, scale), cfg.beta, cfg.omega_max)
    # Accumulated as tensors so a GPU run does not synchronise at every step.
    omega_sum = torch.zeros((), device=hybrid.obs.device)
    clipped = torch.zeros((), device=hybrid.obs.device)
    count = 0
    for _ in range(cfg.epochs):
        perm = torch.from_numpy(rng.permutation(n)).to(hybrid.obs.device)
        for start in range(0, n, cfg.batch_size):
            idx = perm[start : start + cfg.batch_size]
            obs, act = hybrid.obs[idx], hybrid.action[idx]
            pred = actor(obs)
            if fixed is not None:
                omega = fixed[idx]
            else:
                q_pi = critic_values(critics, obs, pred.detach(), hybrid.origin[idx])
                omega = awr_weight(mixed_advantage(q_sa_all[idx], q_pi, weight, cfg.norm, scale), cfg.beta, cfg.omega_max)
            regression_step(actor, opt, obs, act, omega, cfg.max_grad_norm, pred=pred)
            omega_sum += omega.sum()
            clipped += (omega >= cfg.omega_max * (1 - 1e-6)).sum()
            count += len(idx)
            if on_step is not None:
                on_step()
    return {"omega_mean": float(omega_sum) / count, "omega_clipped": float(clipped) / count}


# ---------------------------------------------------------------- one iteration


@dataclass
class ChildRecord:
    parents: tuple[int, int]
    weight: np.ndarray  # (m,) unit target weight
    counts: np.ndarray  # (m,) hybrid rows drawn from each buffer
    stats: dict[str, float]


def make_child(
    returns: np.ndarray,
    actors: Sequence[Actor],
    buffers: Sequence[dict[str, np.ndarray]],
    critics: Sequence[CriticEnsemble],
    *,
    hidden_sizes: Sequence[int],
    child_buffer_size: int,
    weight_norm: str,
    warmup_steps: int,
    warmup_lr: float,
    warmup_batch_size: int,
    adv: AdvantageConfig,
    rng: np.random.Generator,
    torch_seed: int,
    device,
    on_step: Callable[[], None] | None = None,
) -> tuple[Actor, ChildRecord]:
    """One MAPEX iteration's training: parents, target weight, hybrid buffer, warm-up, AWR.

    returns: (n, m) mean returns of the population so far; actors: its n policies.
    """
    parents = select_parents(returns, rng)
    w = target_weight(returns, parents, weight_norm)
    hybrid = build_hybrid(buffers, w, child_buffer_size, rng, device)
    parent_actors = [actors[p] for p in parents]
    a_bar = mean_parent_action(parent_actors, hybrid.obs)
    torch.manual_seed(torch_seed)
    ref = actors[parents[0]]
    child = Actor(hybrid.obs.shape[1], hybrid.action.shape[1], hidden_sizes, (ref.centre - ref.scale).cpu(), (ref.centre + ref.scale).cpu()).to(device)
    warm_up(child, hybrid.obs, a_bar, warmup_steps, warmup_lr, warmup_batch_size, rng)
    _, span = population_scale(returns)
    stats = advantage_weighted_regression(
        child,
        hybrid,
        critics,
        torch.as_tensor(w, dtype=torch.float32, device=device),
        torch.as_tensor(span, dtype=torch.float32, device=device),
        adv,
        rng,
        on_step,
    )
    counts = np.bincount(hybrid.origin.cpu().numpy(), minlength=len(buffers))
    return child.eval(), ChildRecord(parents=parents, weight=w, counts=counts, stats=stats)
