"""One MAPEX iteration's K children trained as one stacked ensemble (`make_children`: with
`children_per_iteration` K > 1, or on CUDA). The steps of one child, and `make_child`, the
reference this is checked against, are in pipeline/extraction/mapex.py.

The K children are one `StackedActor` (stacked weights, one batched matmul per layer for all K)
trained by one Adam over the stacked parameters. Adam is elementwise and each child's loss
touches only its own slice, so no child's update depends on another's; gradient-norm clipping,
the one step that is not elementwise, is done per child. Hybrid buffers of different lengths:
each child keeps its own schedule of minibatches (its own permutation per epoch, its own number
of steps per epoch, its own short last batch), padded to a common (K, batch) shape with masked
rows that weigh nothing and do not count in its mean. A child whose schedule ends before the
others' keeps the weights of its own last step; the trailing padded steps (where Adam's momentum
would still move it) never reach it. On a CPU each child's minibatches come from its numpy
generator exactly as `make_child` draws them, so a child trained among K equals the same child
trained alone up to the float rounding of the batched matmuls. On CUDA they are drawn on the
device from a per-child torch generator (no host sync in the step loop), so CPU and CUDA draw
different (each reproducible) minibatches.

A stacked run checks the children's losses and weights for NaN and infinity
(pipeline.core.finite) every CHECK_EVERY steps and at the end of the warm-up and of the
advantage-weighted regression, raising TrainingDiverged naming the child ("child j of K").
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import torch

from pipeline.core.finite import TrainingDiverged, due, first_nonfinite, weights
from pipeline.core.nets import Actor, CriticEnsemble, StackedActor
from pipeline.core.optim import adam_step, clear_grads
from pipeline.core.pareto import population_scale
from pipeline.core.precision import compute, frozen
from pipeline.core.seeding import torch_generator
from pipeline.extraction.mapex import (
    AdvantageConfig,
    ChildConfig,
    ChildRecord,
    ChildSeeds,
    ChildStart,
    Hybrid,
    awr_weight,
    critic_values,
    make_child,
    mean_parent_action,
    mixed_advantage,
    start_child,
)


@dataclass
class StackedHybrid:
    """K children's hybrid buffers zero-padded to the longest: row i of child j is real iff
    i < lengths[j]."""

    obs: torch.Tensor  # (K, N, obs_dim)
    action: torch.Tensor  # (K, N, act_dim)
    origin: torch.Tensor  # (K, N) int64
    lengths: list[int]  # (K,) rows of each child's own hybrid buffer


def pad_stack(rows: Sequence[torch.Tensor], length: int | None = None) -> torch.Tensor:
    """Tensors (n_j, ...) -> (K, length, ...), zero past each one's rows (length: max n_j)."""
    n = max(len(r) for r in rows) if length is None else length
    out = rows[0].new_zeros((len(rows), n, *rows[0].shape[1:]))
    for j, r in enumerate(rows):
        out[j, : len(r)] = r
    return out


def stack_hybrids(hybrids: Sequence[Hybrid]) -> StackedHybrid:
    return StackedHybrid(
        obs=pad_stack([h.obs for h in hybrids]),
        action=pad_stack([h.action for h in hybrids]),
        origin=pad_stack([h.origin for h in hybrids]),
        lengths=[len(h.obs) for h in hybrids],
    )


def warmup_schedule(
    n: int, steps: int, batch_size: int, rng: np.random.Generator, gen: torch.Generator | None = None, device="cpu"
) -> torch.Tensor:
    """One child's warm-up minibatch rows: (steps, min(batch_size, n)) int64, drawn with
    replacement from `rng` exactly as `warm_up` draws them, or on the device from `gen`."""
    b = min(batch_size, n)
    if gen is not None:
        return torch.randint(0, n, (steps, b), generator=gen, device=gen.device)
    rows = [rng.integers(0, n, size=b) for _ in range(steps)]
    return torch.from_numpy(np.stack(rows) if rows else np.zeros((0, b), np.int64)).to(device)


def epoch_schedule(
    n: int, epochs: int, batch_size: int, rng: np.random.Generator, gen: torch.Generator | None = None, device="cpu"
) -> tuple[torch.Tensor, torch.Tensor]:
    """One child's minibatch rows for `epochs` shuffled passes over its n rows.

    Returns idx (epochs * S, batch_size) int64, S = ceil(n / batch_size) steps per epoch, and
    mask (same shape, 1.0 = a real row, 0.0 = padding of each epoch's short last batch). One
    permutation per epoch, from `rng` exactly as `advantage_weighted_regression` draws them,
    or on the device from `gen`.
    """
    steps = -(-n // batch_size)
    width = steps * batch_size
    dev = gen.device if gen is not None else torch.device(device)
    idx = torch.zeros(epochs, width, dtype=torch.int64, device=dev)
    for e in range(epochs):
        idx[e, :n] = (
            torch.randperm(n, generator=gen, device=dev)
            if gen is not None
            else torch.from_numpy(rng.permutation(n)).to(dev)
        )
    mask = (torch.arange(width, device=dev) < n).float().expand(epochs, width)
    return idx.view(epochs * steps, batch_size), mask.reshape(epochs * steps, batch_size)


def stack_schedules(
    rows: Sequence[torch.Tensor], masks: Sequence[torch.Tensor] | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """K per-child schedules (T_j, b_j) -> one time-major schedule: idx (T, K, b) int32 and
    mask (T, K, b) bool, T = max T_j, b = max b_j, everything past a child's own rows and
    steps masked out (masks: per child, 1 = a real row; default all real).

    int32 and bool keep the whole run's schedule small (epochs x rows x K entries: at the
    paper's 20 epochs of 200k rows with K = 16, 256 MB of indices and 64 MB of mask, where
    int64 and float would take 512 and 256 MB); each step converts its (K, b) slice
    (`step_slice`).
    """
    t, b = max(len(r) for r in rows), max(r.shape[1] for r in rows)
    idx = torch.zeros(t, len(rows), b, dtype=torch.int32, device=rows[0].device)
    mask = torch.zeros(t, len(rows), b, dtype=torch.bool, device=rows[0].device)
    for j, r in enumerate(rows):
        idx[: len(r), j, : r.shape[1]] = r.to(torch.int32)
        mask[: len(r), j, : r.shape[1]] = True if masks is None else masks[j] > 0
    return idx, mask


def step_slice(rows: torch.Tensor, mask: torch.Tensor, t: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Step t of a `stack_schedules` schedule: row indices (K, b) int64 and mask (K, b) float
    (1.0 = a real row, 0.0 = padding)."""
    return rows[t].long(), mask[t].float()


def gather_rows(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """x (K, N) or (K, N, d) at rows idx (K, B) of each child -> (K, B) or (K, B, d).

    Rows of (K, N, d) are read by one `index_select` over the K * N rows (index j * N + i):
    the same values as `torch.gather` along dim 1 (a copy, no arithmetic), measured 2-4x faster
    for d of 6 and 17 (K = 16, N = 200,000: 96 us instead of 438 for the observations, CPU, under
    load). (K, N) keeps `gather`, faster there."""
    if x.dim() == 2:
        return torch.gather(x, 1, idx)
    k, n = x.shape[:2]
    flat = (idx + torch.arange(k, device=idx.device).unsqueeze(1) * n).reshape(-1)
    return x.reshape(k * n, *x.shape[2:]).index_select(0, flat).view(*idx.shape, *x.shape[2:])


def clip_grad_norm_per_child_(params: Sequence[torch.Tensor], max_norm: float) -> torch.Tensor:
    """`torch.nn.utils.clip_grad_norm_` for each child on its own: child j's gradient (slice j
    along dim 0 of every stacked parameter) is scaled by min(1, max_norm / (||g_j|| + 1e-6)),
    ||g_j|| the L2 norm over all of child j's parameters. Returns ||g_j|| (K,)."""
    grads = [p.grad for p in params if p.grad is not None]
    norms = torch.stack([torch.linalg.vector_norm(g.flatten(1), dim=1) for g in grads])  # (P, K)
    total = torch.linalg.vector_norm(norms, dim=0)
    coef = torch.clamp(max_norm / (total + 1e-6), max=1.0)
    for g in grads:
        g.mul_(coef.view(-1, *([1] * (g.dim() - 1))))
    return total


def stacked_regression_step(
    actor: StackedActor, opt: torch.optim.Optimizer, obs, target, mask, weight=None, max_grad_norm=None, pred=None
) -> torch.Tensor:
    """One Adam step of every child j on its own loss: the mean over its real rows b of
    weight_jb * ||pi_j(s_jb) - target_jb||^2 (weight None = 1); `regression_step` for K at once.

    obs (K, B, obs_dim), target (K, B, act_dim), mask and weight (K, B). The summed loss gives
    child j's slice exactly the gradient of its own loss. Returns the K losses (detached).
    """
    pred = actor(obs) if pred is None else pred
    sq = ((pred - target) ** 2).sum(dim=-1)
    w = mask if weight is None else weight * mask
    loss = (sq * w).sum(dim=1) / mask.sum(dim=1).clamp(min=1)
    clear_grads(opt)
    loss.sum().backward()
    if max_grad_norm is not None:
        clip_grad_norm_per_child_(list(actor.parameters()), max_grad_norm)
    adam_step(opt)
    return loss.detach()


def check_children(what: str, loss: torch.Tensor, actor: StackedActor, step: int) -> None:
    """Raise TrainingDiverged naming the first child ("child j of K") whose loss (K,) or
    weights are not finite (`what`: the loss's name)."""
    bad = first_nonfinite([(what, loss), *weights("a child weight", actor)])
    if bad is None:
        return
    k = len(loss)
    j = next((j for j in range(k) if first_nonfinite([("", loss[j]), *[("", p[j]) for p in actor.parameters()]])), None)
    raise TrainingDiverged(*bad, step, during=f"child {j + 1} of {k}" if j is not None else None)


def _adam(actor: StackedActor, lr: float, precision: str = "fp32") -> torch.optim.Optimizer:
    # Fused on CUDA and in bf16: one kernel per parameter tensor instead of a dozen elementwise
    # ones (pipeline/core/optim.py); the plain Adam in fp32 on a CPU, as before the switch.
    if actor.scale.is_cuda or precision == "bf16":
        return torch.optim.Adam(actor.parameters(), lr=lr, fused=True)
    return torch.optim.Adam(actor.parameters(), lr=lr)


def stacked_warm_up(
    actor: StackedActor,
    obs: torch.Tensor,
    target: torch.Tensor,
    rows: torch.Tensor,
    mask: torch.Tensor,
    lr: float,
    precision: str = "fp32",
) -> None:
    """`warm_up` for K children at once (paper eq. L_init): obs (K, N, o), target (K, N, a)
    = each child's mean parent action; rows, mask (T, K, b) from `stack_schedules`."""
    opt = _adam(actor, lr, precision)
    for t in range(len(rows)):
        idx, real = step_slice(rows, mask, t)
        o = gather_rows(obs, idx)
        with compute(precision, o.device):
            pred = actor(o)
        loss = stacked_regression_step(actor, opt, o, gather_rows(target, idx), real, pred=pred)
        if due(t + 1) or t + 1 == len(rows):
            check_children("the warm-up loss", loss, actor, t + 1)


@torch.no_grad()
def fixed_weights(
    actor: StackedActor,
    data: StackedHybrid,
    critics: Sequence[CriticEnsemble],
    q_sa: torch.Tensor,
    weight: torch.Tensor,
    scale: torch.Tensor,
    cfg: AdvantageConfig,
    gather: bool | None = None,
    precision: str = "fp32",
) -> torch.Tensor:
    """omega of every hybrid row with Q(s, pi_new(s)) computed once, after warm-up
    (advantage_recompute = once): (K, N), each child over its own rows as
    `advantage_weighted_regression` computes it (zscore over its whole hybrid buffer)."""
    out = torch.zeros(q_sa.shape[:2], device=q_sa.device)
    for j, n in enumerate(data.lengths):
        obs = data.obs[j, :n]
        with torch.random.fork_rng(devices=[]):  # building an Actor draws from the global generator
            child = actor.unstack(j).to(obs.device)
        pi_new = mean_parent_action([child], obs, precision=precision)
        q_pi = critic_values(critics, obs, pi_new, data.origin[j, :n], gather=gather)
        out[j, :n] = awr_weight(mixed_advantage(q_sa[j, :n], q_pi, weight[j], cfg.norm, scale), cfg.beta, cfg.omega_max)
    return out


def stacked_awr(
    actor: StackedActor,
    data: StackedHybrid,
    critics: Sequence[CriticEnsemble],
    weight: torch.Tensor,
    scale: torch.Tensor,
    cfg: AdvantageConfig,
    rows: torch.Tensor,
    mask: torch.Tensor,
    ends: Sequence[int],
    on_step: Callable[[], None] | None = None,
    gather: bool | None = None,
    precision: str = "fp32",
) -> list[dict[str, float]]:
    """`advantage_weighted_regression` for K children at once (paper Step 3).

    weight (K, m): each child's target weight; scale (m,) objective ranges; rows, mask
    (T, K, B) from `stack_schedules` of each child's `epoch_schedule`; ends (K,): the steps
    T_j of child j's own schedule. One index tensor per step gathers the rows' obs, action,
    origin, Q(s, a) and loss terms, so row b of child j is weighted by the omega of that same
    row. No host sync inside the loop on CUDA (no .item(), boolean indexing or numpy) but the
    finiteness check every CHECK_EVERY steps. Child j's weights are kept as they are after its
    step T_j. Returns per-child statistics of the weights (mean, fraction clipped at omega_max).
    precision: as `advantage_weighted_regression`'s.
    """
    k, m = len(data.lengths), critics[0].n_members // 2
    critics = [frozen(c, precision) for c in critics]
    q_sa = pad_stack(
        [
            critic_values(critics, data.obs[j, :n], data.action[j, :n], data.origin[j, :n], gather=gather)
            for j, n in enumerate(data.lengths)
        ],
        data.obs.shape[1],
    )
    fixed = (
        fixed_weights(actor, data, critics, q_sa, weight, scale, cfg, gather, precision)
        if cfg.recompute == "once"
        else None
    )
    opt = _adam(actor, cfg.lr, precision)
    params = list(actor.parameters())
    finishing: dict[int, list[int]] = {}
    for j, t in enumerate(ends):
        finishing.setdefault(t, []).append(j)
    final: dict[int, list[torch.Tensor]] = {}
    omega_sum = torch.zeros(k, device=q_sa.device)
    clipped = torch.zeros(k, device=q_sa.device)
    for t in range(len(rows)):
        idx, real = step_slice(rows, mask, t)
        obs, act = gather_rows(data.obs, idx), gather_rows(data.action, idx)
        with compute(precision, obs.device):
            pred = actor(obs)
        if fixed is not None:
            omega = gather_rows(fixed, idx)
        else:
            origin = gather_rows(data.origin, idx)
            q_pi = critic_values(
                critics, obs.flatten(0, 1), pred.detach().flatten(0, 1), origin.flatten(), gather=gather
            ).view(k, -1, m)
            mixed = mixed_advantage(gather_rows(q_sa, idx), q_pi, weight, cfg.norm, scale, real)
            omega = awr_weight(mixed, cfg.beta, cfg.omega_max)
        loss = stacked_regression_step(actor, opt, obs, act, real, omega, cfg.max_grad_norm, pred=pred)
        if due(t + 1):
            check_children("the advantage-weighted loss", loss, actor, t + 1)
        omega_sum += (omega * real).sum(dim=1)
        clipped += ((omega >= cfg.omega_max * (1 - 1e-6)) * real).sum(dim=1)
        if t + 1 < len(rows):
            for j in finishing.get(t + 1, []):
                final[j] = [p.detach()[j].clone() for p in params]
        if on_step is not None:
            on_step()
    with torch.no_grad():
        for j, snapshot in final.items():
            for p, v in zip(params, snapshot):
                p[j].copy_(v)
    if len(rows):
        check_children("the advantage-weighted loss", loss, actor, len(rows))
    total = [cfg.epochs * n for n in data.lengths]
    sums, clips = omega_sum.tolist(), clipped.tolist()
    return [{"omega_mean": sums[j] / total[j], "omega_clipped": clips[j] / total[j]} for j in range(k)]


def train_stacked(
    children: Sequence[ChildStart],
    critics: Sequence[CriticEnsemble] | None,
    cfg: ChildConfig,
    span: np.ndarray,
    rngs: Sequence[np.random.Generator],
    gens: Sequence[torch.Generator | None],
    on_step: Callable[[], None] | None = None,
    gather: bool | None = None,
) -> tuple[StackedActor, list[dict[str, float]]]:
    """Warm-up and AWR of K started children as one stacked ensemble; child j draws its
    minibatch rows from rngs[j] (host) or gens[j] (device), warm-up rows first, as `make_child`.

    span: (m,) the population's objective ranges. critics: None only when cfg.adv.epochs == 0
    (they are read by the advantage-weighted epochs alone). Returns the trained stack and
    per-child stats.
    """
    data = stack_hybrids([c.hybrid for c in children])
    if min(data.lengths) == 0:
        raise ValueError(f"a child's hybrid buffer is empty (lengths {data.lengths})")
    device = data.obs.device
    actor = StackedActor([c.actor for c in children])
    rows, mask = stack_schedules(
        [
            # each child's own warm-up steps: 0 for one interpolated from its parents (extract.init)
            warmup_schedule(n, c.warmup_steps, cfg.warmup_batch_size, rng, gen, device)
            for n, rng, gen, c in zip(data.lengths, rngs, gens, children)
        ]
    )
    stacked_warm_up(
        actor,
        data.obs,
        pad_stack([c.a_bar for c in children], data.obs.shape[1]),
        rows,
        mask,
        cfg.warmup_lr,
        cfg.precision,
    )
    if cfg.adv.epochs == 0:
        return actor, [{"omega_mean": float("nan"), "omega_clipped": float("nan")} for _ in children]
    sched = [
        epoch_schedule(n, cfg.adv.epochs, cfg.adv.batch_size, rng, gen, device)
        for n, rng, gen in zip(data.lengths, rngs, gens)
    ]
    rows, mask = stack_schedules([i for i, _ in sched], [m for _, m in sched])
    weight = torch.as_tensor(np.stack([c.weight for c in children]), dtype=torch.float32, device=device)
    scale = torch.as_tensor(span, dtype=torch.float32, device=device)
    stats = stacked_awr(
        actor,
        data,
        critics,
        weight,
        scale,
        cfg.adv,
        rows,
        mask,
        [len(i) for i, _ in sched],
        on_step,
        gather,
        cfg.precision,
    )
    return actor, stats


def make_children(
    returns: np.ndarray,
    actors: Sequence[Actor],
    buffers: Sequence[dict[str, np.ndarray]],
    critics: Sequence[CriticEnsemble] | None,
    cfg: ChildConfig,
    seeds: Sequence[ChildSeeds],
    device,
    *,
    stacked: bool | None = None,
    device_rows: bool | None = None,
    gather: bool | None = None,
    on_step: Callable[[], None] | None = None,
) -> list[tuple[Actor, ChildRecord]]:
    """One iteration's K = len(seeds) children, each made from the same population (returns
    (n, m), actors) with its own seeds; K = 1 is Algorithm 1's iteration.

    stacked: train them as one `StackedActor` (None: unless K = 1 on a CPU, which runs the
    reference `make_child`). device_rows: draw minibatch rows on the device from each
    child's seeds.rows generator (None: on CUDA). gather: the critic lookup path (see
    `critic_values`). critics may be None when cfg.adv.epochs == 0 (warm-up only reads none).
    Returns (actor on `device`, record) per child, in the order of `seeds`.
    """
    if critics is None and cfg.adv.epochs > 0:
        raise ValueError(
            f"{cfg.adv.epochs} advantage-weighted epochs need the specialists' critics, but none were given"
        )
    device = torch.device(device)
    if stacked is None:
        stacked = len(seeds) > 1 or device.type == "cuda"
    if not stacked:
        out = []
        for j, s in enumerate(seeds):
            try:
                out.append(make_child(returns, actors, buffers, critics, cfg, s, device, on_step))
            except TrainingDiverged as exc:
                raise exc.about(during=f"child {j + 1} of {len(seeds)}") if len(seeds) > 1 else exc
        return out
    device_rows = device.type == "cuda" if device_rows is None else device_rows
    rngs = [np.random.default_rng(s.numpy) for s in seeds]
    gens = [torch_generator(s.rows, device) if device_rows else None for s in seeds]
    children = [start_child(returns, actors, buffers, cfg, rng, s.torch, device) for rng, s in zip(rngs, seeds)]
    stack, stats = train_stacked(children, critics, cfg, population_scale(returns)[1], rngs, gens, on_step, gather)
    with torch.random.fork_rng(devices=[]):  # building an Actor draws from the global generator
        trained = [stack.unstack(j).to(device).eval() for j in range(len(children))]
    return [(a, c.record(len(buffers), s)) for a, c, s in zip(trained, children, stats)]
