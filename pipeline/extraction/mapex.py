"""MAPEX extraction (paper, Algorithm 1 and section "Method", steps 1-3).

Each iteration: find the non-dominated set of the population, pick a gap on it by roulette
wheel over gap sizes, derive the target weight from the parents' centroid, build a hybrid
buffer from the specialists' buffers in proportion to the weight, warm a fresh policy up on
the mean parent action, then train it by mixed-advantage-weighted regression.

Step 1 (pipeline.extraction.gaps, re-exported here): for N = 2 objectives the paper's rule,
the front sorted along objective 0, a gap = an edge between neighbours, drawn with probability
proportional to its length, its 2 endpoints the parents. For N >= 3 the front is triangulated
(projected onto the hyperplane orthogonal to (1, ..., 1), then Delaunay), a gap = a facet of
N vertices drawn with probability proportional to its (N - 1)-dimensional volume, its N
vertices the parents. Either way the target weight is the unit vector towards the centroid of
the parents' normalised returns.

Deviations from the paper, each a param unless it is a necessary reading:
- Edge lengths (facet sizes) and the centroid are measured in objective space normalised by the
  population's per-objective range (necessary: raw returns differ in scale by orders of
  magnitude and can be negative, so a raw centroid can point anywhere, even away from both
  parents).
- N >= 3 objectives: the paper defines the gap for N = 2 only and leaves N >= 3 to future
  work; the facet rule above is this project's extension (docs/n_objectives.md), with
  documented fallbacks for degenerate fronts (fewer parents on a front of lower affine rank,
  the per-objective best policies on a front of one point), and `facet_bridge_ratio`: only
  the gaps on the front's surface are drawn (facets across a thin curved front's hull are
  left out; its steps are 2-parent gaps). N = 2 is unchanged.
- A front of one point (no gap of positive size): the policies best on each objective are the
  parents (a case the paper does not cover).
- `advantage_norm`: `none` mixes the raw advantages A_m with a weight w computed from
  range-normalised returns: a mix of units that neither the paper (raw returns and raw
  advantages throughout) nor a consistent reading uses. It is a deviation, kept as the default
  only because every measurement so far was taken with it (there is no measured evidence for
  another choice yet). `objective_range` (each A_m divided by objective m's population range,
  the units of w) is the consistent reading; `zscore` is the precursor code's.
- `advantage_recompute: once` computes Q(s, pi_new(s)) once after warm-up (precursor code)
  instead of at every step (Algorithm 1).
- `children_per_iteration` K > 1 (default 1 = Algorithm 1): K children per iteration, each
  with parents drawn by the same roulette from the same front (the population at the start of
  the iteration: a child never sees its siblings), its own hybrid buffer and its own RNG
  streams, trained together as one stacked ensemble (`make_children`), then all added.
- `precision: bf16` (default fp32, which the paper's results assume): the children's matrix
  products in bfloat16, the critics and parents cast once, master weights, Adam and every sum
  in fp32 (pipeline/core/precision.py).
- `init: interpolate` (default warmup = the paper; the hybrid extraction, not in the paper):
  a child starts from its parents' weights mixed with equal coefficients (`interpolated_start`)
  instead of a random network, without the warm-up unless `warmup_after_interpolate`; a child
  whose parents cannot be mixed into one (`interpolation_problem`) starts as the paper's and
  says so in its record. The paper's advantage-weighted phase follows either way.
An advantage always weights exactly the row it was computed for (the precursor code paired
them with resampled rows, a bug not reproduced here).

Two implementations of a child's training, checked against each other by the tests:
- `make_child` (here): one child with plain modules, the reference. On a CPU with K = 1 it is
  what the stage runs: bit for bit the code from before children were batched.
- `make_children` (pipeline/extraction/children.py): K children as one stacked ensemble.

Both check their losses and the child's weights for NaN and infinity (pipeline.core.finite)
every CHECK_EVERY steps and at the end of the warm-up and of the advantage-weighted
regression, raising TrainingDiverged (stacked: naming the child, "child j of K").
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Callable, NamedTuple, Sequence

import numpy as np
import torch

from pipeline.core.alignment import MixOptions, mixer
from pipeline.core.finite import check_finite, due, weights
from pipeline.core.mixing import architecture_problem, mix_actors
from pipeline.core.nets import Actor, CriticEnsemble
from pipeline.core.optim import adam_step, child_adam, clear_grads
from pipeline.core.pareto import population_scale
from pipeline.core.precision import compute, frozen

# Step 1 (gaps, parents, target weight) lives in pipeline.extraction.gaps; re-exported here.
from pipeline.extraction.gaps import front_edges as front_edges
from pipeline.extraction.gaps import select_parents as select_parents
from pipeline.extraction.gaps import target_weight as target_weight

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
def mean_parent_action(
    parents: Sequence[Actor], obs: torch.Tensor, chunk: int = 65_536, precision: str = "fp32"
) -> torch.Tensor:
    """a_bar(s) = mean over parents of pi_p(s), for every row of obs (N, obs_dim) -> (N, act_dim).
    precision bf16: each parent runs as a bfloat16 copy made once here (the mean is fp32)."""
    parents = [frozen(p, precision) for p in parents]
    out = []
    for i in range(0, len(obs), chunk):
        o = obs[i : i + chunk]
        out.append(torch.stack([p(o) for p in parents]).mean(dim=0))
    return torch.cat(out)


def regression_step(
    actor: Actor, opt: torch.optim.Optimizer, obs, target, weight=None, max_grad_norm=None, pred=None
) -> torch.Tensor:
    """One Adam step on mean_b weight_b * ||pi(s_b) - target_b||^2 (weight None = 1).

    `pred` = actor(obs) if the caller already computed it (with grad), to avoid a second pass.
    """
    pred = actor(obs) if pred is None else pred
    sq = ((pred - target) ** 2).sum(dim=-1)
    loss = (sq * weight).mean() if weight is not None else sq.mean()
    clear_grads(opt)  # opt.zero_grad(set_to_none=True) without its bookkeeping
    loss.backward()
    if max_grad_norm is not None:
        torch.nn.utils.clip_grad_norm_(actor.parameters(), max_grad_norm)
    adam_step(opt)  # opt.step(), past its bookkeeping for a fused Adam (pipeline/core/optim.py)
    return loss.detach()


def warm_up(
    actor: Actor,
    obs: torch.Tensor,
    target: torch.Tensor,
    steps: int,
    lr: float,
    batch_size: int,
    rng: np.random.Generator,
    precision: str = "fp32",
) -> None:
    """Regress `actor` onto `target` actions at hybrid states (paper eq. L_init), `steps` steps;
    the actor's forward in `precision` (pipeline.core.precision), the loss and Adam in fp32."""
    opt = child_adam(actor.parameters(), lr, precision)
    n = len(obs)
    for t in range(1, steps + 1):
        idx = torch.from_numpy(rng.integers(0, n, size=min(batch_size, n))).to(obs.device)
        o = obs[idx]
        with compute(precision, obs.device):
            pred = actor(o)
        loss = regression_step(actor, opt, o, target[idx], pred=pred)
        if due(t) or t == steps:
            check_finite([("the warm-up loss", loss), *weights("a child weight", actor)], t)


# ---------------------------------------------------------------- step 2-3: mixed advantage


@torch.no_grad()
def critic_values(
    critics: Sequence[CriticEnsemble],
    obs: torch.Tensor,
    action: torch.Tensor,
    origin: torch.Tensor,
    chunk: int = 65_536,
    gather: bool | None = None,
) -> torch.Tensor:
    """Q^(k)_m(s, a) for each row with k = the row's origin: (B, m), min over the twin heads.

    Each row is evaluated only by the critics trained on the buffer it came from
    (paper, "Secondary Critics"). Rows are processed `chunk` at a time to bound memory. The
    values are fp32 whatever the critics' dtype (bfloat16 copies: pipeline.core.precision) or
    an enclosing autocast.
    gather: evaluate every critic on every row and pick each row's by its origin, the CUDA
    path (no boolean indexing, hence no host sync); None = on CUDA only. The CPU path runs
    each critic on its own rows alone, which is less compute.
    """
    gather = obs.is_cuda if gather is None else gather
    if len(obs) > chunk:
        return torch.cat(
            [
                critic_values(critics, obs[i : i + chunk], action[i : i + chunk], origin[i : i + chunk], chunk, gather)
                for i in range(0, len(obs), chunk)
            ]
        )
    if gather:
        # On a GPU, evaluating every critic on every row and selecting costs little, while
        # indexing by a boolean mask would make the host wait for the device at every step.
        every = torch.stack([c.twin_min(obs, action).T for c in critics])  # (K, B, m)
        return every.gather(0, origin.view(1, -1, 1).expand(1, -1, every.shape[2])).squeeze(0)
    m = critics[0].n_members // 2
    out = torch.empty(len(obs), m, device=obs.device)
    for k, critic in enumerate(critics):
        rows = (origin == k).nonzero(as_tuple=True)[0]
        if len(rows):
            out[rows] = critic.twin_min(obs[rows], action[rows]).T.to(out.dtype)
    return out


def mixed_advantage(
    q_sa: torch.Tensor,
    q_pi: torch.Tensor,
    weight: torch.Tensor,
    norm: str,
    scale: torch.Tensor | None = None,
    mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """A_mixed = w . (Q(s, a) - Q(s, pi_new(s))) per row (paper eqs. "mixed advantage").

    q_sa, q_pi: (B, m) with weight (m,) -> (B,); or (K, B, m) with weight (K, m), one target
    weight per child -> (K, B). scale: (m,) objective ranges for norm="objective_range".
    norm="zscore" standardises A_mixed over the rows given: the whole hybrid buffer when
    Q(s, pi_new(s)) is computed once (the precursor code), each minibatch when recomputed;
    with `mask` ((K, B), 1 = a real row, 0 = padding) over each child's real rows only.
    """
    adv = q_sa - q_pi
    if norm == "objective_range":
        adv = adv / scale
    mixed = adv @ weight if weight.dim() == 1 else (adv @ weight.unsqueeze(-1)).squeeze(-1)
    if norm == "zscore":
        if mask is None:
            mixed = (mixed - mixed.mean()) / (mixed.std(unbiased=False) + 1e-8)
        else:
            n = mask.sum(dim=-1, keepdim=True).clamp(min=1)
            mean = (mixed * mask).sum(dim=-1, keepdim=True) / n
            std = ((((mixed - mean) ** 2) * mask).sum(dim=-1, keepdim=True) / n).sqrt()
            mixed = (mixed - mean) / (std + 1e-8)
    return mixed


def awr_weight(mixed: torch.Tensor, beta: float, omega_max: float) -> torch.Tensor:
    """omega = min(exp(A_mixed / beta), omega_max) (paper Step 3), computed without overflow."""
    return torch.exp(torch.clamp(mixed / beta, max=float(np.log(omega_max))))


@dataclass(frozen=True, kw_only=True)
class AdvantageConfig:
    """How a child's advantage-weighted regression runs (paper Step 3): the `extract` params
    epochs, beta, omega_max, lr, batch_size, max_grad_norm, advantage_recompute and
    advantage_norm. Keyword-only: four of its fields are floats, easy to swap by position."""

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
    critics: Sequence[CriticEnsemble] | None,
    weight: torch.Tensor,
    scale: torch.Tensor,
    cfg: AdvantageConfig,
    rng: np.random.Generator,
    on_step: Callable[[], None] | None = None,
    precision: str = "fp32",
) -> dict[str, float]:
    """Train `actor` for cfg.epochs shuffled passes over the hybrid buffer (paper Step 3).

    Row b of a minibatch is weighted by omega computed from that same row's (s, a): the
    minibatch indices are drawn once and used for Q(s, a), Q(s, pi_new(s)) and the loss alike.
    Returns summary statistics of the weights (mean, fraction clipped at omega_max). With
    cfg.epochs == 0 nothing is trained and no critic is read (critics may be None).
    precision bf16 (pipeline.core.precision): the critics run as bfloat16 copies (made here
    unless they already are), the actor's forward under autocast; Q-values, advantages, omega,
    the loss and Adam stay fp32.
    """
    n = len(hybrid.obs)
    if cfg.epochs == 0 or n == 0:
        return {"omega_mean": float("nan"), "omega_clipped": float("nan")}
    critics = [frozen(c, precision) for c in critics]
    opt = child_adam(actor.parameters(), cfg.lr, precision)
    q_sa_all = critic_values(critics, hybrid.obs, hybrid.action, hybrid.origin)
    fixed = None
    if cfg.recompute == "once":
        with torch.no_grad():
            # pi_new(s) for every row, chunked and without grad (a "mean" over one policy)
            pi_new = mean_parent_action([actor], hybrid.obs, precision=precision)
            q_pi_all = critic_values(critics, hybrid.obs, pi_new, hybrid.origin)
        fixed = awr_weight(mixed_advantage(q_sa_all, q_pi_all, weight, cfg.norm, scale), cfg.beta, cfg.omega_max)
    # Accumulated as tensors so a GPU run does not synchronise at every step.
    omega_sum = torch.zeros((), device=hybrid.obs.device)
    clipped = torch.zeros((), device=hybrid.obs.device)
    count = t = 0
    for _ in range(cfg.epochs):
        perm = torch.from_numpy(rng.permutation(n)).to(hybrid.obs.device)
        for start in range(0, n, cfg.batch_size):
            idx = perm[start : start + cfg.batch_size]
            obs, act = hybrid.obs[idx], hybrid.action[idx]
            with compute(precision, obs.device):
                pred = actor(obs)
            if fixed is not None:
                omega = fixed[idx]
            else:
                q_pi = critic_values(critics, obs, pred.detach(), hybrid.origin[idx])
                omega = awr_weight(
                    mixed_advantage(q_sa_all[idx], q_pi, weight, cfg.norm, scale), cfg.beta, cfg.omega_max
                )
            loss = regression_step(actor, opt, obs, act, omega, cfg.max_grad_norm, pred=pred)
            omega_sum += omega.sum()
            clipped += (omega >= cfg.omega_max * (1 - 1e-6)).sum()
            count += len(idx)
            t += 1
            if due(t):
                check_finite([("the advantage-weighted loss", loss), *weights("a child weight", actor)], t)
            if on_step is not None:
                on_step()
    check_finite([("the advantage-weighted loss", loss), *weights("a child weight", actor)], t)
    return {"omega_mean": float(omega_sum) / count, "omega_clipped": float(clipped) / count}


# ---------------------------------------------------------------- one child: the reference


@dataclass(frozen=True, kw_only=True)
class ChildConfig:
    """How a child is made: the `extract` params that shape one child's training (keyword-only)."""

    hidden_sizes: tuple[int, ...]
    child_buffer_size: int  # target rows of the hybrid buffer
    weight_norm: str  # "l2" (paper) | "l1" (precursor)
    warmup_steps: int
    warmup_lr: float
    warmup_batch_size: int
    adv: AdvantageConfig
    facet_bridge_ratio: float | None = None  # N >= 3: which facets the roulette draws from (gaps.front_gaps)
    precision: str = "fp32"  # resolved (pipeline.core.precision): "fp32" or "bf16"
    # the hybrid extraction (not in the paper; `start_child`): "warmup" (the paper) or "interpolate"
    init: str = "warmup"
    warmup_after_interpolate: bool = False  # init "interpolate": warm up from the interpolated start too
    # init "interpolate": how the parents are mixed (extract.align, repair, mix, regmean_alpha;
    # pipeline.core.alignment); the default is the plain linear mix
    mixing: MixOptions = field(default_factory=MixOptions)
    mix_states: int = 4096  # repair or regmean: the hybrid buffer's first rows they measure on


class ChildSeeds(NamedTuple):
    """A child's independent random streams."""

    numpy: int  # parents, hybrid rows and, with host-drawn rows (CPU), every minibatch
    torch: int  # the child's initial weights
    rows: int  # minibatch rows drawn on the device (CUDA): a torch generator there


@dataclass
class ChildRecord:
    parents: tuple[int, ...]  # m policy ids for m objectives (fewer on a degenerate front)
    weight: np.ndarray  # (m,) unit target weight
    counts: np.ndarray  # (m,) hybrid rows drawn from each buffer
    stats: dict[str, float]
    init: str | None = None  # init "interpolate": "interpolated" or "warmup" (the fallback); None: the paper's
    fallback: str | None = None  # why the child fell back to the paper's warm-up (init "interpolate")


@dataclass
class ChildStart:
    """A child before its training: parents, target weight, hybrid buffer, warm-up targets."""

    parents: tuple[int, ...]
    weight: np.ndarray  # (m,) unit target weight
    hybrid: Hybrid
    a_bar: torch.Tensor  # (N, act_dim) mean parent action at each hybrid state ((0, act_dim) without warm-up)
    actor: Actor  # freshly initialised (or interpolated from its parents), on the device
    warmup_steps: int  # the warm-up's steps for this child (0: none, an interpolated start)
    init: str | None = None  # as ChildRecord.init
    fallback: str | None = None  # as ChildRecord.fallback

    def record(self, n_buffers: int, stats: dict[str, float]) -> ChildRecord:
        counts = np.bincount(self.hybrid.origin.cpu().numpy(), minlength=n_buffers)
        return ChildRecord(
            parents=self.parents, weight=self.weight, counts=counts, stats=stats, init=self.init, fallback=self.fallback
        )


def interpolation_problem(parents: Sequence[Actor], hidden_sizes: Sequence[int]) -> str | None:
    """Why a child of `hidden_sizes` cannot start from its parents' mixed weights (None if it
    can): every parent must be a plain `Actor` (not one that normalises observations, nor a
    program brought in whole) of the children's hidden sizes, all with the same action bounds
    (pipeline.core.mixing.architecture_problem), so that the mix is a child like any other (one
    stack of K children shares one shape)."""
    for p in parents:
        if type(p) is not Actor:
            return f"a parent is a {type(p).__name__}, not a plain actor of the children's architecture"
        widths = [m.out_features for m in p.net if isinstance(m, torch.nn.Linear)][:-1]
        if widths != list(hidden_sizes):
            return f"a parent has hidden sizes {widths}, the children extract.hidden_sizes {list(hidden_sizes)}"
    return architecture_problem(parents, [f"parent {i}" for i in range(len(parents))])


def interpolated_start(
    parents: Sequence[Actor], mixing: MixOptions | None = None, obs: torch.Tensor | None = None
) -> Actor:
    """The hybrid extraction's child before training (not in the paper): its parents' weights
    mixed with equal coefficients 1/N (pipeline.core.mixing.mix_actors), on the CPU.

    Why equal coefficients: the target weight is the direction of the centroid of the parents'
    normalised returns, so the point of the parents' simplex it points at is that centroid, the
    mix 1/N of each parent (exactly, where returns are linear in the mixing weights). The
    target weight's own components (one per objective) name no parent unless the parents are
    the specialists themselves, where both readings give the same mix for 2 objectives.

    `mixing` (extract.align, repair, mix; not in the paper): the mix aligned, repaired on `obs`
    or merged by RegMean, through pipeline.core.alignment.mixer, the interpolation stage's own
    implementation. Parents that reach here are mapex MLPs (`interpolation_problem`), which can
    always be aligned."""
    weights = [1 / len(parents)] * len(parents)
    if mixing is None or mixing.plain:
        return mix_actors(parents, weights)
    cpu = [copy.deepcopy(p).cpu() for p in parents] if any(p.net[0].weight.is_cuda for p in parents) else parents
    make, _ = mixer(cpu, mixing, None if obs is None else obs.detach().float().cpu())
    return make(weights)


def start_child(
    returns: np.ndarray,
    actors: Sequence[Actor],
    buffers: Sequence[dict[str, np.ndarray]],
    cfg: ChildConfig,
    rng: np.random.Generator,
    torch_seed: int,
    device,
) -> ChildStart:
    """Steps 1-2 for one child: parents by roulette, target weight, hybrid buffer, the mean parent
    action a_bar(s) at its states, and a fresh actor initialised from `torch_seed`.

    returns: (n, m) mean returns of the population; actors: its n policies. Draws from `rng`
    in a fixed order (parents, then hybrid rows); torch's global generator is left untouched.

    cfg.init "interpolate" (the hybrid extraction, not in the paper): the actor is instead the
    parents' weights mixed (`interpolated_start`), with no warm-up unless
    cfg.warmup_after_interpolate; where the parents cannot be mixed (`interpolation_problem`)
    the child falls back to the paper's start, and its record says why.
    """
    parents = select_parents(returns, rng, cfg.facet_bridge_ratio)
    w = target_weight(returns, parents, cfg.weight_norm)
    hybrid = build_hybrid(buffers, w, cfg.child_buffer_size, rng, device)
    mine = [actors[p] for p in parents]
    if cfg.init == "interpolate":
        fallback = interpolation_problem(mine, cfg.hidden_sizes)
        if fallback is None:
            steps = cfg.warmup_steps if cfg.warmup_after_interpolate else 0
            a_bar = (
                mean_parent_action(mine, hybrid.obs, precision=cfg.precision) if steps else hybrid.action[:0].clone()
            )
            obs = hybrid.obs[: cfg.mix_states] if cfg.mixing.needs_states else None
            actor = interpolated_start(mine, cfg.mixing, obs).to(device)
            return ChildStart(parents, w, hybrid, a_bar, actor, steps, "interpolated")
    a_bar = mean_parent_action(mine, hybrid.obs, precision=cfg.precision)
    ref = actors[parents[0]]
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(torch_seed)
        actor = Actor(
            hybrid.obs.shape[1],
            hybrid.action.shape[1],
            cfg.hidden_sizes,
            (ref.centre - ref.scale).cpu(),
            (ref.centre + ref.scale).cpu(),
        )
    if cfg.init == "interpolate":
        return ChildStart(parents, w, hybrid, a_bar, actor.to(device), cfg.warmup_steps, "warmup", fallback)
    return ChildStart(parents, w, hybrid, a_bar, actor.to(device), cfg.warmup_steps)


def make_child(
    returns: np.ndarray,
    actors: Sequence[Actor],
    buffers: Sequence[dict[str, np.ndarray]],
    critics: Sequence[CriticEnsemble] | None,
    cfg: ChildConfig,
    seeds: ChildSeeds,
    device,
    on_step: Callable[[], None] | None = None,
) -> tuple[Actor, ChildRecord]:
    """One MAPEX iteration's training (Algorithm 1): parents, target weight, hybrid buffer,
    warm-up, AWR, with plain modules. Every random draw comes from `seeds` (seeds.rows unused:
    minibatch rows come from the numpy stream, also on CUDA, at one host-to-device copy each).
    critics: None only when cfg.adv.epochs == 0 (warm-up only reads no critic).
    """
    rng = np.random.default_rng(seeds.numpy)
    child = start_child(returns, actors, buffers, cfg, rng, seeds.torch, device)
    warm_up(
        child.actor,
        child.hybrid.obs,
        child.a_bar,
        child.warmup_steps,
        cfg.warmup_lr,
        cfg.warmup_batch_size,
        rng,
        cfg.precision,
    )
    _, span = population_scale(returns)
    stats = advantage_weighted_regression(
        child.actor,
        child.hybrid,
        critics,
        torch.as_tensor(child.weight, dtype=torch.float32, device=device),
        torch.as_tensor(span, dtype=torch.float32, device=device),
        cfg.adv,
        rng,
        on_step,
        cfg.precision,
    )
    return child.actor.eval(), child.record(len(buffers), stats)
