"""Post-hoc secondary critics: fit Q^(k)_m offline on specialist k's replay buffer D_k.

Paper, section "Secondary Critics", "Practical note": critics for every objective m can be
trained after the fact from the transitions of D_k and the rewards of objective m, with no
environment interaction. Q^(k)_m is the value of specialist k's own policy pi_k for
objective m, so the Bellman target uses pi_k's action at s'. (The authors' precursor code
used the best policy of the population here instead; that is a deviation from the paper
and is not reproduced.)

Each gradient step reuses the TD3 pieces that train the joint critics (`pipeline.specialists.td3`):

    y_m = r_m + gamma * (1 - terminated) * min_h Q'_{m,h}(s', clip(pi_k(s') + clip(noise)))

with twin heads per objective, soft-updated target critics, and time-limit truncation
treated as non-terminal (the target bootstraps through a truncated transition). Only the
critics learn: pi_k is frozen, so this is policy evaluation of pi_k on off-line data.
"""

from __future__ import annotations

import copy
import math
from typing import Callable, NamedTuple, Sequence

import numpy as np
import torch

from pipeline.core.buffer import Batch, batch_at
from pipeline.core.finite import check_finite, due, weights
from pipeline.core.nets import Actor, CriticEnsemble
from pipeline.core.precision import compute, frozen, resolve
from pipeline.params.fit_critics import FitCriticsParams
from pipeline.specialists.td3 import critic_loss, polyak_update, smoothed_target_action, td3_targets


class FitCheck(NamedTuple):
    step: int  # gradient steps done when checked
    loss: float  # critic loss of that step
    error: float  # the stopping rule's error (lower is better), e.g. mean normalised fidelity error


class FittedCritics(NamedTuple):
    online: CriticEnsemble  # 2 * len(objectives) members, member 2*j + h = head h of objectives[j]
    target: CriticEnsemble  # its soft-updated target copy
    final_loss: float  # critic loss of the last gradient step (sum over members of the MSE)
    steps: int = 0  # gradient steps run
    best_step: int = 0  # step of the kept weights (== steps without checks)
    checks: tuple[FitCheck, ...] = ()  # every fidelity check, in order


def init_critics(
    obs_dim: int, act_dim: int, hidden_sizes: Sequence[int], n_objectives: int, rng: np.random.Generator
) -> CriticEnsemble:
    """A fresh ensemble with two heads per objective, initialised from a seed drawn from `rng`.

    `CriticEnsemble` draws its initial weights from torch's global generator; forking that
    generator keeps this function free of global side effects while staying reproducible.
    """
    seed = int(rng.integers(0, 2**63 - 1))
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return CriticEnsemble(obs_dim, act_dim, hidden_sizes, 2 * n_objectives)


def posthoc_step(
    critic: CriticEnsemble,
    critic_target: CriticEnsemble,
    optimizer: torch.optim.Optimizer,
    target_policy: Actor,
    batch: Batch,
    objectives: Sequence[int],
    cfg: FitCriticsParams,
    generator: torch.Generator,
    precision: str = "fp32",
) -> torch.Tensor:
    """One gradient step of every critic on `batch`; returns the (detached) loss.

    batch.reward is (B, n_objectives_env); the columns `objectives` are the targets' rewards,
    in member order. The target critics are not updated here (see `fit_posthoc_critics`).
    precision bf16: the critics' forward passes under autocast (the frozen target policy is
    passed as a bfloat16 copy, pipeline.core.precision.frozen), the noise, targets and loss in fp32.
    """
    reward = batch.reward[:, list(objectives)]  # (B, n_obj)
    device = batch.obs.device
    with torch.no_grad():  # the target policy is frozen: in bf16 already cast (no autocast around it)
        next_a = smoothed_target_action(target_policy, batch.next_obs, cfg.policy_noise, cfg.noise_clip, generator)
    with compute(precision, device):
        y = td3_targets(critic_target, batch.next_obs, next_a, reward, batch.terminated, cfg.gamma)  # (n_obj, B)
        loss = critic_loss(critic, batch.obs, batch.action, y)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()
    return loss.detach()


def fit_posthoc_critics(
    data: dict[str, np.ndarray],
    target_policy: Actor,
    objectives: Sequence[int],
    cfg: FitCriticsParams,
    rng: np.random.Generator,
    generator: torch.Generator,
    device: torch.device | str = "cpu",
    on_step: Callable[[int, torch.Tensor], None] | None = None,
    error: Callable[[CriticEnsemble], float] | None = None,
) -> FittedCritics:
    """Fit Q^(k)_m for each m in `objectives` on the transitions `data` of buffer D_k.

    data: the arrays of `pipeline.core.buffer.load_buffer` (T rows; obs (T, obs_dim), action
    (T, act_dim), reward (T, n_objectives_env), next_obs, terminated (T,) ...).
    target_policy: pi_k, whose action at s' enters the Bellman target (frozen; the stage
    passes the specialist's TD3 target actor when the checkpoint has one, as the joint
    critics used). rng draws the initial weights' seed and every batch's row indices;
    generator (on `device`) draws the target-smoothing noise. With the same rng/generator
    states the result is bitwise identical on CPU.
    on_step(step, loss) is called after each gradient step (1-based).

    Stopping: with `error` given and cfg.check_every > 0, error(online critic) is computed every
    cfg.check_every steps (the stage passes the mean normalised error of Q(s, pi_k(s)) against
    Monte-Carlo returns on the buffer's last episodes). The weights with the lowest error are
    kept, and fitting stops once cfg.patience checks in a row improved on that best by less than
    cfg.min_improvement, or after cfg.steps steps. The paper gives no rule; the precursor's fixed
    5,000 steps left critics predicting a tenth of the return (issue 11), so this fits until the
    critics stop getting closer to the returns they estimate. Without checks: exactly cfg.steps.

    Raises TrainingDiverged (pipeline.core.finite) if the loss or a critic weight is not
    finite, checked every CHECK_EVERY steps and at the end (also when the kept weights are
    from before the divergence: a fit that diverged is not trusted).

    Precision: cfg.precision resolved on `device` at the critics' width (pipeline.core.precision);
    with bf16 the frozen target policy is cast to bfloat16 once and the gradient steps run
    their forward passes in bf16; the fidelity checks (`error`) see the fp32 master weights.
    """
    n = len(data["obs"])
    if n == 0:
        raise ValueError("cannot fit critics on an empty buffer")
    obs_dim, act_dim = data["obs"].shape[1], data["action"].shape[1]
    critic = init_critics(obs_dim, act_dim, cfg.hidden_sizes, len(objectives), rng).to(device)
    critic_target = copy.deepcopy(critic).requires_grad_(False)
    precision = resolve(cfg.precision, device, max(cfg.hidden_sizes))
    policy = frozen(copy.deepcopy(target_policy).to(device).eval().requires_grad_(False), precision)
    # fused: one kernel per parameter tensor (same Adam update, fewer element-wise ops).
    optimizer = torch.optim.Adam(critic.parameters(), lr=cfg.lr, fused=True)
    loss = torch.zeros(())
    checking = error is not None and cfg.check_every > 0
    checks: list[FitCheck] = []
    best, best_step, best_state, stale = math.inf, 0, None, 0  # lowest error, its step and weights
    step = 0
    for step in range(1, cfg.steps + 1):
        batch = batch_at(data, rng.integers(0, n, size=cfg.batch_size), device)
        loss = posthoc_step(critic, critic_target, optimizer, policy, batch, objectives, cfg, generator, precision)
        if step % cfg.target_update_freq == 0:
            polyak_update(critic, critic_target, cfg.tau)
        if on_step is not None:
            on_step(step, loss)
        if due(step):
            check_finite([("critic loss", loss), *weights("a critic weight", critic)], step)
        if checking and (step % cfg.check_every == 0 or step == cfg.steps):
            critic.eval()
            err = float(error(critic))
            critic.train()
            checks.append(FitCheck(step, float(loss), err))
            if not math.isfinite(err):
                err = math.inf  # undefined fidelity (no scorable state) never counts as better
            stale = 0 if err < best - cfg.min_improvement else stale + 1
            if err < best:  # keep the closest weights, even when the gain is below min_improvement
                best, best_step = err, step
                best_state = (copy.deepcopy(critic.state_dict()), copy.deepcopy(critic_target.state_dict()))
            if stale >= cfg.patience:
                break
    check_finite([("critic loss", loss), *weights("a critic weight", critic, critic_target)], step)
    if best_state is not None:
        critic.load_state_dict(best_state[0])
        critic_target.load_state_dict(best_state[1])
    else:
        best_step = step
    return FittedCritics(critic.eval(), critic_target.eval(), float(loss), step, best_step, tuple(checks))
