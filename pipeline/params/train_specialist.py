"""Section `train_specialist`: TD3 specialists with secondary critics.

Defaults are the paper's TD3 table (appendix, "PDERL and TD3 hyperparameters"); the paper
trains each specialist for 2M env steps (1M on Swimmer). params.yaml overrides them with a
small quickstart preset.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from pipeline.params.common import Strict


class TrainSpecialistParams(Strict):
    total_steps: int = Field(2_000_000, gt=0, description="env steps per specialist (paper: 2M; Swimmer 1M)")
    learning_starts: int = Field(25_000, ge=1, description="uniform-random action steps before updates begin")
    buffer_size: int = Field(1_000_000, gt=0, description="replay capacity; older rows are overwritten")
    batch_size: int = Field(256, gt=0, description="minibatch size for each update")
    hidden_sizes: list[int] = Field([256, 256], min_length=1, description="hidden layer widths (actor and critics)")
    actor_lr: float = Field(3e-4, gt=0, le=1, description="Adam learning rate of the actor")
    critic_lr: float = Field(3e-4, gt=0, le=1, description="Adam learning rate of the critic ensemble")
    gamma: float = Field(0.99, ge=0, lt=1, description="discount factor")
    tau: float = Field(0.005, gt=0, le=1, description="Polyak rate of the target networks")
    exploration_noise: float = Field(0.1, ge=0, description="std of Gaussian action noise, times the action half-range")
    policy_noise: float = Field(0.2, ge=0, description="std of the target-policy smoothing noise")
    noise_clip: float = Field(0.5, ge=0, description="clip of the target-policy smoothing noise")
    policy_freq: int = Field(2, ge=1, description="critic updates per actor/target update")
    secondary_critics: bool = Field(True, description="also train critics for every other objective (joint MAPEX)")
    device: Literal["auto", "cpu", "cuda"] = Field("auto", description="'auto' picks cuda when present")
    batched: bool = Field(
        True,
        description="train all specialists of a stage in one stacked process (each exactly as alone); "
        "false: one after another",
    )
    processes: int = Field(
        1,
        ge=1,
        description="worker processes the stage splits its specialists over, side by side (at most one per "
        "objective; each uses MAPEX_TORCH_THREADS threads); the specialists of a process stack as `batched` says. "
        "A specialist trained alone gives other bits than one stacked with another, so this changes the artifacts",
    )
    cuda_graphs: bool = Field(True, description="on CUDA, replay each update as captured CUDA graphs (false: eager)")
    checkpoint_every: int = Field(
        50_000,
        ge=0,
        description="env steps between resumable checkpoints (OUT/specialist_state_obj*.pt: networks, optimizers, "
        "replay buffers, RNGs, envs); a rerun with the same params, code, device and threads resumes; 0: off",
    )

    keep_best_every: int = Field(
        0,
        ge=0,
        description="keep-best selection, a deviation from plain TD3 and from the paper (which does not say which "
        "policy it keeps; off, 0, the default: the final actor). When > 0, after every env step t that is a multiple "
        "of it and past learning_starts, and after the last step, each specialist's actor is evaluated "
        "deterministically (keep_best_episodes episodes on an env of its own, mean return on its own objective), and "
        "the best-scoring actor and its target actor are written instead of the final ones (critics and buffer stay "
        "final; training itself is unchanged). Why: TD3's policy oscillates late in short trainings, so the final "
        "weights can score far below the best seen; the TD3 paper's evaluations and Stable-Baselines3's EvalCallback "
        "(best_model) select the same way",
    )
    keep_best_episodes: int = Field(
        3,
        ge=1,
        description="deterministic episodes per keep-best check and specialist (env seeds from seed, objective and "
        "check index; they cost env steps, no training draws)",
    )

    @model_validator(mode="after")
    def _consistent(self) -> "TrainSpecialistParams":
        if any(h <= 0 for h in self.hidden_sizes):
            raise ValueError(f"hidden_sizes must be positive, got {self.hidden_sizes}")
        if self.learning_starts < self.batch_size:
            raise ValueError(f"learning_starts ({self.learning_starts}) must be >= batch_size ({self.batch_size})")
        if self.learning_starts >= self.total_steps:
            raise ValueError(f"learning_starts ({self.learning_starts}) must be < total_steps ({self.total_steps})")
        if self.keep_best_every > self.total_steps:
            raise ValueError(
                f"keep_best_every ({self.keep_best_every}) must be <= total_steps ({self.total_steps}); 0 turns "
                "keep-best off"
            )
        return self
