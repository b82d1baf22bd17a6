"""Section `train_specialist`: the run of the TD3 specialists (one per objective, with secondary critics).

The agent itself (networks, learning rates, noises, replay, start timesteps) is section `td3`
(pipeline/params/td3.py), shared with PDERL and MOPDERL. This section holds what only the
specialists' run reads: its length (the paper trains each specialist for 2M env steps, 1M on
Swimmer), how the specialists share the machine, checkpoints and keep-best selection.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from pipeline.params.common import PrecisionChoice, Strict, precision_field
from pipeline.params.td3 import TD3Params


class TrainSpecialistParams(Strict):
    total_steps: int = Field(2_000_000, gt=0, description="env steps per specialist (paper: 2M; Swimmer 1M)")
    device: Literal["auto", "cpu", "cuda"] = Field("auto", description="'auto' picks cuda when present")
    precision: PrecisionChoice = precision_field("the specialists' TD3 updates (acting in the env stays fp32)")
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
        if self.keep_best_every > self.total_steps:
            raise ValueError(
                f"keep_best_every ({self.keep_best_every}) must be <= total_steps ({self.total_steps}); 0 turns "
                "keep-best off"
            )
        return self


def check_against_td3(cfg: TrainSpecialistParams, td3: TD3Params) -> None:
    """The checks across the two sections a specialist run reads; ValueError naming both keys."""
    if td3.shared_prefix_steps >= cfg.total_steps:
        raise ValueError(
            f"td3.shared_prefix_steps ({td3.shared_prefix_steps}) must be < train_specialist.total_steps "
            f"({cfg.total_steps}): the specialists fork from the prefix and train their own objective after it"
        )
    if td3.learning_starts >= cfg.total_steps:
        raise ValueError(
            f"td3.learning_starts ({td3.learning_starts}) must be < train_specialist.total_steps ({cfg.total_steps})"
        )
