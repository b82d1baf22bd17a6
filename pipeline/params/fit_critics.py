"""Section `fit_critics`: post-hoc critics Q^(k)_m fitted offline on specialist k's buffer.

Paper, "Secondary Critics" / "Practical note": when specialists were trained without
secondary critics, Q^(k)_m can be fitted afterwards from the transitions of D_k and the
reward of objective m. The defaults follow the authors' precursor code (5000 gradient steps,
batch 256, Adam 3e-4, gamma 0.99, tau 0.005, targets soft-updated every 2 steps), except
target-policy smoothing: the paper defines every critic by the TD3 rule, so smoothing is on
(0.2 / 0.5, as for the specialists); the precursor used none (set policy_noise: 0 for that),
and the budget: the precursor's fixed 5,000 steps left the critics far from the returns they
estimate, so fitting runs until their fidelity (pipeline.critics.fidelity, scored with the actor they
are fitted with) stops improving, at most `steps` steps (pipeline.critics.posthoc.fit_posthoc_critics).

The stopping rule's scoring settings are this section's own (not `critic_fidelity`'s), so a
change to the fidelity report reruns no fit.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, PositiveInt

from pipeline.params.common import PrecisionChoice, Strict, precision_field


class FitCriticsParams(Strict):
    steps: int = Field(
        100_000,
        gt=0,
        description="most gradient steps of the critic ensemble (fewer when fidelity stops improving; precursor code: 5000 fixed)",
    )
    check_every: int = Field(
        1000,
        ge=0,
        description="gradient steps between fidelity checks of the stopping rule (0: no checks, exactly `steps` steps)",
    )
    patience: int = Field(
        5, ge=1, description="stop after this many checks in a row without improving the best fidelity error"
    )
    min_improvement: float = Field(
        0.005, ge=0, description="a check improves if it lowers the best mean normalised error by more than this"
    )
    fidelity_episodes: int = Field(
        10,
        gt=0,
        description="stopping rule: score on the buffer's last this-many episodes (as critic_fidelity.episodes)",
    )
    tail_tolerance: float = Field(
        0.01,
        gt=0,
        lt=1,
        description="stopping rule: drop cut-episode states whose missing tail weight gamma^H exceeds this (as critic_fidelity)",
    )
    batch_size: int = Field(256, gt=0, description="transitions per gradient step, drawn uniformly with replacement")
    lr: float = Field(3e-4, gt=0, le=1, description="Adam learning rate of the critic ensemble")
    gamma: float = Field(0.99, ge=0, lt=1, description="discount factor of the fitted critics")
    tau: float = Field(0.005, gt=0, le=1, description="Polyak rate of the target critics")
    policy_noise: float = Field(
        0.2, ge=0, description="std of the target-policy smoothing noise (0: no smoothing, as the precursor)"
    )
    noise_clip: float = Field(0.5, ge=0, description="clip of the target-policy smoothing noise")
    target_update_freq: int = Field(2, ge=1, description="gradient steps per soft update of the target critics")
    hidden_sizes: list[PositiveInt] = Field([256, 256], min_length=1, description="hidden layer widths of every critic")
    device: Literal["auto", "cpu", "cuda"] = Field(
        "auto", description="'auto' picks cuda when present; results are bitwise reproducible on cpu"
    )
    precision: PrecisionChoice = precision_field(
        "the critics' fit (the fidelity checks of the stopping rule stay fp32)",
        auto="bf16 where the hardware has bfloat16 natively and the critics' hidden width is >= 256, else fp32",
    )
