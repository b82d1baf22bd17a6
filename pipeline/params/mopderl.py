"""Section `mopderl`: phase 2 of the MOPDERL baseline (stage mopderl, pipeline/baselines/mopderl.py).

MOPDERL's phase 1 is one PDERL run per objective: the PDERL specialists of stage
train_pderl. Phase 2, configured here, merges their populations and evolves them with
NSGA-II selection and multi-objective distillation crossover while both RL agents keep
training. The RL agents are this project's TD3 with secondary critics, so their
hyperparameters (learning rates, batch, replay capacity, noise, ...) are read from the
`td3` section, exactly as train_pderl reads them for phase 1.

Defaults are the paper's where it gives a value (the frame budget, appendix table
"Environment interaction budgets") and the authors' public MOPDERL code otherwise (see each
description). `total_frames` and `eval_episodes` left at null take their per-environment
values (`resolved`).
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from pipeline.params.common import PrecisionChoice, Strict, precision_field
from pipeline.params.env_facts import mopderl_values

# Per env (paper appendix, "Environment interaction budgets": stage-2 frames; the authors' code,
# `num_evals`: episodes per fitness evaluation) in presets/envs.yaml, `mopderl`; an env without an
# entry gets these.
DEFAULT_STAGE2_FRAMES = 2_000_000
DEFAULT_EVAL_EPISODES = 1


class MopderlParams(Strict):
    total_frames: int | None = Field(
        None,
        gt=0,
        description="phase-2 env frames: every evaluation episode and RL exploration episode, the evaluation of the "
        "starting population included. null = the paper's stage-2 budget for env.id (2M; Hopper 1.75M, Swimmer 1M). "
        "The last generation started below the budget runs to its end",
    )
    population_size: int = Field(
        20, ge=2, description="individuals kept by NSGA-II survivor selection (authors' code: 10 per objective, 20)"
    )
    children: int = Field(
        20,
        ge=0,
        description="distillation-crossover children of population pairs per generation (authors' code: "
        "population size); one more child per RL agent comes on top",
    )
    tournament_size: int = Field(
        4,
        ge=2,
        description="entrants (drawn with replacement) of each parent tournament on (Pareto rank, crowding) "
        "(authors' code: 4)",
    )
    eval_episodes: int | None = Field(
        None,
        ge=1,
        description="episodes per new individual; its fitness is their mean return vector. null = the "
        "authors' code for env.id (1; Hopper 3, Walker2d 5)",
    )
    mini_buffer_size: int = Field(
        8_000,
        gt=0,
        description="states kept per individual (authors' code: 8,000, half of it from each parent at crossover)",
    )
    mutation_prob: float = Field(
        0.9,
        ge=0,
        le=1,
        description="chance that each individual (survivors and this generation's children) also "
        "gets a proximally mutated clone (authors' code: 0.9); each RL actor always gets one",
    )
    mutation_std: float = Field(
        0.05, ge=0, description="std of the Gaussian weight noise before scaling (authors' code: 0.05)"
    )
    mutation_states: int = Field(
        256, ge=1, description="states the action sensitivity of a mutation is measured on (authors' code: 256)"
    )
    mutation_min_sensitivity: float = Field(
        0.01, gt=0, description="sensitivities below this are raised to it before dividing (authors' code: 0.01)"
    )
    crossover_transitions: int = Field(
        4_000, ge=1, description="latest states taken from each parent to distil a child on (authors' code: 4,000)"
    )
    crossover_epochs: int = Field(
        12, ge=1, description="passes over the child's distillation states (authors' code: 12)"
    )
    crossover_batch_size: int = Field(128, ge=1, description="minibatch of the distillation (authors' code: 128)")
    crossover_lr: float = Field(
        1e-3, gt=0, le=1, description="Adam learning rate of the distillation (authors' code: 1e-3)"
    )
    crossover_action_penalty: float = Field(
        1 / 128,
        ge=0,
        description="weight of mean(a^2) beside the summed squared action error, as in train_pderl",
    )
    rl_updates_per_frame: float = Field(
        1.0,
        ge=0,
        description="TD3 updates of each RL agent per frame added to its replay buffer in a generation, rounded "
        "down (authors' code: 1.0). Below 1 is a cheaper deviation",
    )
    checkpoint_every: int = Field(
        1, ge=1, description="generations between resumable checkpoints (RESUME_DIR/mopderl/seedS)"
    )
    device: Literal["auto", "cpu", "cuda"] = Field("auto", description="'auto' picks cuda when present")
    precision: PrecisionChoice = precision_field("the RL agents' TD3 updates (episodes and evolution stay fp32)")

    @model_validator(mode="after")
    def _consistent(self) -> "MopderlParams":
        for key in ("crossover_transitions", "mutation_states"):
            if getattr(self, key) > self.mini_buffer_size:
                raise ValueError(f"{key} ({getattr(self, key)}) must be <= mini_buffer_size ({self.mini_buffer_size})")
        return self

    def resolved(self, env_id: str) -> "MopderlParams":
        """A copy with total_frames and eval_episodes filled in for `env_id` where they are null."""
        fill = {}
        if self.total_frames is None or self.eval_episodes is None:
            env = mopderl_values(env_id) or {
                "total_frames": DEFAULT_STAGE2_FRAMES,
                "eval_episodes": DEFAULT_EVAL_EPISODES,
            }
            fill = {k: env[k] for k in ("total_frames", "eval_episodes") if getattr(self, k) is None}
        return self.model_copy(update=fill)
