"""Aligned interpolation: putting two or more actors' hidden units in correspondence before their
weights are mixed, and correcting the mix's activations on states (issue 61; not in the paper).

Mixing independently trained networks, theta = sum_i w_i theta_i (pipeline.core.mixing), averages
hidden unit j of one actor with hidden unit j of another, though nothing made them compute the
same feature: the mix's returns sag in the middle of the path (the "barrier"). Three remedies
from the model-merging literature, each for mapex's MLP actor (Linear, ReLU, ..., Linear):

- **Weight matching** (Ainsworth, Hayase & Srinivasa, "Git Re-Basin", ICLR 2023): permute each
  other actor's hidden units so that its weights are as close as possible to the first actor's.
  A permutation of a hidden layer's units, applied to that layer's rows (and bias) and to the next
  layer's columns, leaves the network's function unchanged; the matching maximises
  sum_l <W_l^ref, P_l W_l P_{l-1}^T> + <b_l^ref, P_l b_l> by coordinate descent over the layers,
  each step a linear assignment problem (scipy.optimize.linear_sum_assignment), until no layer's
  permutation changes. Data-free.
- **REPAIR** (Jordan et al., "REPAIR: REnormalizing Permuted Activations for Interpolation
  Repair", ICLR 2023): after mixing with weights w, rescale each hidden unit's preactivation so
  that its mean and standard deviation on a set of states are the w-weighted means of the
  endpoints' (each endpoint's statistics measured on its own network), layer by layer from the
  input, by an affine change of that layer's weight row and bias.
- **RegMean** (Jin et al., "Dataless Knowledge Fusion by Merging Weights of Language Models",
  ICLR 2023): instead of averaging a linear layer's weights, take the least-squares merge that
  best reproduces every endpoint's outputs on its own layer inputs X_i:
  [W | b] = (sum_i w_i G_i)^-1 sum_i w_i G_i [W_i | b_i]^T with G_i the Gram matrix of [X_i, 1],
  its off-diagonal entries scaled by alpha (their regularisation; alpha = 1 is the plain least
  squares, alpha = 0 the linear mix for each output unit up to its input scales).

Weight matching is what the other two need first (they too assume unit j of one actor is unit j
of the other); `mixer` composes them, and both the interpolation baseline and the hybrid's
interpolated start build their actors through it (one implementation).

Actors that are not mapex MLPs (TorchScript or torch.export programs) cannot be mixed at all
(`architecture_problem`); any MLP of one architecture can be aligned, so an alignment problem is
only reported for architectures `architecture_problem` lets through but this module does not know
(`alignment_problem`), and the callers then mix without aligning, saying so in one line.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment
from torch import nn

from pipeline.core.mixing import mix_actors
from pipeline.core.nets import Actor, NormalizedActor

ALIGN_MODES = ("none", "weights")
MIX_RULES = ("linear", "regmean")
MAX_SWEEPS = 100  # coordinate-descent passes of weight matching (a 2-layer actor settles in a few)


def linears(actor: Actor) -> list[nn.Linear]:
    """The actor's Linear layers, input to output."""
    return [m for m in actor.net if isinstance(m, nn.Linear)]


def alignment_problem(actor: nn.Module) -> str | None:
    """Why this actor's hidden units cannot be permuted here (None if they can): its net must be
    Linear layers with one ReLU between consecutive ones, nothing else."""
    if not isinstance(actor, Actor):
        return f"a {type(actor).__name__} has no hidden layers this alignment knows"
    mods = list(actor.net)
    expect_linear = True
    for m in mods:
        if expect_linear and not isinstance(m, nn.Linear):
            return f"its net has a {type(m).__name__} where a Linear layer was expected"
        if not expect_linear and not isinstance(m, nn.ReLU):
            return f"its net has a {type(m).__name__} between Linear layers (only ReLU can be permuted through here)"
        expect_linear = not expect_linear
    if expect_linear:  # ended on a ReLU
        return "its net ends on an activation, not a Linear layer"
    return None


def _net_input(actor: Actor, obs: torch.Tensor) -> torch.Tensor:
    """What the actor's first Linear layer reads for raw observations `obs` (float32)."""
    if isinstance(actor, NormalizedActor):
        z = (obs.to(torch.float64) - actor.obs_mean) / actor.obs_std
        return torch.minimum(torch.maximum(z, -actor.obs_clip), actor.obs_clip).to(torch.float32)
    return obs.to(torch.float32)


@torch.no_grad()
def layer_inputs(actor: Actor, obs: torch.Tensor) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """For states `obs` (B, obs_dim): each Linear layer's input (B, in_l) and each hidden layer's
    preactivation (B, out_l), in the actor's own forward pass."""
    x = _net_input(actor, obs)
    inputs, pre = [], []
    layers = linears(actor)
    for i, layer in enumerate(layers):
        inputs.append(x)
        z = layer(x)
        if i < len(layers) - 1:
            pre.append(z)
            x = torch.relu(z)
    return inputs, pre


def _permuted(actor: Actor, perms: Sequence[np.ndarray]) -> Actor:
    """A copy of `actor` whose hidden layer l's units are reordered by perms[l] (new unit i is old
    unit perms[l][i]); the same function."""
    out = copy.deepcopy(actor)
    layers = linears(out)
    with torch.no_grad():
        for li, p in enumerate(perms):
            idx = torch.as_tensor(p, dtype=torch.long)
            layers[li].weight.copy_(layers[li].weight[idx])
            layers[li].bias.copy_(layers[li].bias[idx])
            layers[li + 1].weight.copy_(layers[li + 1].weight[:, idx])
    return out


def weight_matching(ref: Actor, other: Actor) -> list[np.ndarray]:
    """Per hidden layer, the permutation of `other`'s units (new unit i = old unit p[i]) that
    maximises its weights' inner product with `ref`'s (Git Re-Basin's weight matching): coordinate
    descent over the layers in order, each a linear assignment, from the identity, until a whole
    pass changes nothing (at most MAX_SWEEPS passes). Deterministic. Both actors must pass
    `alignment_problem` and have one architecture."""
    a = [(li.weight.detach().double().numpy(), li.bias.detach().double().numpy()) for li in linears(ref)]
    b = [(li.weight.detach().double().numpy(), li.bias.detach().double().numpy()) for li in linears(other)]
    if [w.shape for w, _ in a] != [w.shape for w, _ in b]:
        raise ValueError("weight matching needs actors of one architecture")
    hidden = len(a) - 1
    perms = [np.arange(a[li][0].shape[0]) for li in range(hidden)]
    for _ in range(MAX_SWEEPS):
        changed = False
        for li in range(hidden):
            wa, ba = a[li]
            wb, bb = b[li]
            # B's incoming weights with its previous layer already reordered (columns), its
            # outgoing weights with the next layer's units reordered (rows)
            wb_in = wb[:, perms[li - 1]] if li > 0 else wb
            wb_out = b[li + 1][0][perms[li + 1]] if li + 1 < hidden else b[li + 1][0]
            score = wa @ wb_in.T + np.outer(ba, bb) + a[li + 1][0].T @ wb_out
            _, cols = linear_sum_assignment(score, maximize=True)
            if not np.array_equal(cols, perms[li]):
                # only a strictly better assignment counts as a change (ties keep the current one)
                old = score[np.arange(len(cols)), perms[li]].sum()
                new = score[np.arange(len(cols)), cols].sum()
                if new > old + 1e-12 * max(1.0, abs(old)):
                    perms[li] = cols
                    changed = True
        if not changed:
            break
    return perms


def align_to_first(actors: Sequence[Actor]) -> list[Actor]:
    """The actors with every one after the first permuted to match the first (`weight_matching`);
    the first unchanged. Each computes what it computed before."""
    return [actors[0]] + [_permuted(a, weight_matching(actors[0], a)) for a in actors[1:]]


def _stats(z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    z = z.double()
    return z.mean(0), z.std(0, unbiased=False)


@torch.no_grad()
def repair(mixed: Actor, actors: Sequence[Actor], weights: Sequence[float], obs: torch.Tensor) -> Actor:
    """REPAIR: a copy of `mixed` whose hidden layers' preactivations on `obs` have, unit by unit,
    mean sum_i w_i mean_i and standard deviation sum_i w_i std_i, where mean_i and std_i are the
    unit's statistics in actor i's own forward pass on `obs`; corrected from the input layer up,
    each layer after the ones below it. A unit the mix leaves constant on `obs` (std below 1e-8)
    is shifted only."""
    targets = []
    for actor in actors:
        _, pre = layer_inputs(actor, obs)
        targets.append([_stats(z) for z in pre])
    out = copy.deepcopy(mixed)
    layers = linears(out)
    for li in range(len(layers) - 1):
        mean_t = sum(float(w) * t[li][0] for w, t in zip(weights, targets))
        std_t = sum(float(w) * t[li][1] for w, t in zip(weights, targets))
        _, pre = layer_inputs(out, obs)
        mean_m, std_m = _stats(pre[li])
        gain = torch.where(std_m > 1e-8, std_t / std_m.clamp_min(1e-8), torch.ones_like(std_m))
        w64, b64 = layers[li].weight.double(), layers[li].bias.double()
        layers[li].weight.copy_((w64 * gain[:, None]).float())
        layers[li].bias.copy_(((b64 - mean_m) * gain + mean_t).float())
    return out


@torch.no_grad()
def regmean(actors: Sequence[Actor], weights: Sequence[float], obs: torch.Tensor, alpha: float) -> Actor:
    """RegMean: an actor whose every Linear layer is the w-weighted least-squares merge of the
    actors' layers on their own layer inputs for states `obs` (bias as a constant input), the Gram
    matrices' off-diagonal entries scaled by `alpha`; computed in float64 (a small ridge keeps the
    solve defined when a unit is dead on every state). Buffers and class are the first actor's, as
    `mix_actors` makes them. Zero weights take no part, so a vertex w = e_k gives actor k's layers
    back (up to the solve's rounding)."""
    used = [(a, float(w)) for a, w in zip(actors, weights) if w != 0]
    out = mix_actors(actors, weights)  # the buffers and class; every layer is overwritten below
    ins = [layer_inputs(a, obs)[0] for a, _ in used]
    for li, layer in enumerate(linears(out)):
        lhs, rhs = 0, 0
        for (actor, w), x in zip(used, ins):
            src = linears(actor)[li]
            xa = torch.cat([x[li].double(), torch.ones(len(x[li]), 1, dtype=torch.float64)], 1)
            g = xa.T @ xa
            g = alpha * g + (1 - alpha) * torch.diag(torch.diag(g))
            theta = torch.cat([src.weight.double(), src.bias.double()[:, None]], 1)  # (out, in + 1)
            lhs = lhs + w * g
            rhs = rhs + w * g @ theta.T
        ridge = 1e-9 * float(torch.trace(lhs)) / len(lhs) + 1e-12
        merged = torch.linalg.solve(lhs + ridge * torch.eye(len(lhs), dtype=torch.float64), rhs).T
        layer.weight.copy_(merged[:, :-1].float())
        layer.bias.copy_(merged[:, -1].float())
    return out.eval()


@dataclass(frozen=True)
class MixOptions:
    """How a mix of specialists is made (params `interpolate.align`, `repair`, `mix`,
    `regmean_alpha`): the defaults are the plain linear mix of pipeline.core.mixing."""

    align: str = "none"
    repair: bool = False
    mix: str = "linear"
    regmean_alpha: float = 0.9

    @property
    def needs_states(self) -> bool:
        return self.repair or self.mix == "regmean"

    @property
    def plain(self) -> bool:
        return self == MixOptions()

    def describe(self) -> str:
        parts = ["aligned (weight matching)" if self.align == "weights" else "unaligned"]
        parts.append("RegMean" if self.mix == "regmean" else "linear")
        if self.repair:
            parts.append("REPAIR")
        return ", ".join(parts)


def mixer(
    actors: Sequence[Actor], options: MixOptions, obs: torch.Tensor | None = None
) -> tuple[Callable[[Sequence[float]], Actor], str | None]:
    """A function w -> mixed actor under `options`, and the one line to report when an option had
    to be dropped (None when every option applies). Alignment is computed once here; REPAIR and
    RegMean read `obs` (raw states, float32), which they need. Actors that cannot be aligned
    (`alignment_problem`) are mixed unaligned, and with neither REPAIR nor RegMean (both assume
    corresponding units), which the line says."""
    if options.align not in ALIGN_MODES:
        raise ValueError(f"align {options.align!r}: expected one of {list(ALIGN_MODES)}")
    if options.mix not in MIX_RULES:
        raise ValueError(f"mix {options.mix!r}: expected one of {list(MIX_RULES)}")
    if options.needs_states and obs is None:
        raise ValueError("REPAIR and RegMean need states")
    fallback = None
    if not options.plain:
        problems = [p for p in map(alignment_problem, actors) if p is not None]
        if problems:
            fallback = f"cannot align these actors ({problems[0]}): mixed linearly, unaligned and unrepaired"
            return (lambda w: mix_actors(actors, w)), fallback
    aligned = align_to_first(actors) if options.align == "weights" else list(actors)

    def make(w: Sequence[float]) -> Actor:
        if options.mix == "regmean":
            actor = regmean(aligned, w, obs, options.regmean_alpha)
        else:
            actor = mix_actors(aligned, w)
        if options.repair:
            actor = repair(actor, [a for a, x in zip(aligned, w) if x != 0], [x for x in w if x != 0], obs)
        return actor.eval()

    return make, fallback


def buffer_states(buffers: Sequence[dict[str, np.ndarray]], count: int, seed: int) -> torch.Tensor:
    """`count` states in all, drawn without replacement and in equal shares from each buffer's
    observations (fewer where a buffer holds fewer), with generator `seed`: the states REPAIR and
    RegMean measure on. Deterministic for the same buffers, count and seed."""
    rng = np.random.default_rng(seed)
    share = max(1, count // max(1, len(buffers)))
    parts = []
    for data in buffers:
        obs = data["obs"]
        take = min(share, len(obs))
        idx = np.sort(rng.choice(len(obs), size=take, replace=False))
        parts.append(np.asarray(obs[idx], dtype=np.float32))
    return torch.from_numpy(np.concatenate(parts, 0))
