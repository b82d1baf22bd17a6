"""Section `train_pderl`: PDERL specialists (paper: "specialists are trained using PDERL").

One PDERL run per objective, which is the warm-up stage of MOPDERL: a population of actors
evolved by tournament selection, distillation crossover and proximal mutation beside one RL
agent that learns from every transition the population and itself collect.

The RL agent is this project's TD3 with secondary critics, so its hyperparameters (network
widths, learning rates, batch, replay capacity, start timesteps, noise, ...) are read from the
`td3` section, as the paper's table shares them between TD3 and PDERL. The values below are
PDERL's own: the paper's table gives population 10 and mini buffer 50,000; the others are
those of the public PDERL code, as the paper's authors ran it (see each description). Nothing
of `train_specialist` is read: PDERL's budget is `total_frames`.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from pipeline.params.common import PrecisionChoice, Strict, precision_field


def n_elites(elite_fraction: float, population_size: int) -> int:
    """Elites kept unchanged each generation: floor(fraction * size), at least one."""
    return max(1, int(elite_fraction * population_size))


class TrainPderlParams(Strict):
    total_frames: int = Field(
        2_000_000,
        gt=0,
        description="env frames per objective, every population evaluation and RL episode included "
        "(paper: 2M per MAPEX specialist, Swimmer 1M; MOPDERL's warm-up 1M). The last generation "
        "started below the budget runs to its end, then a final evaluation of every actor follows",
    )
    population_size: int = Field(10, ge=2, description="actors in the population (paper: 10)")
    processes: int = Field(
        1,
        ge=1,
        description="worker processes the stage's objectives are split over, side by side (at most one per "
        "objective; each uses MAPEX_TORCH_THREADS threads). Each PDERL run is the same in any process: the "
        "artifacts do not change",
    )
    elite_fraction: float = Field(
        0.1,
        gt=0,
        lt=1,
        description="fraction of the population kept unchanged as elites, at least one "
        "(PDERL code: 0.1; 0.2 on Hopper, Walker2d, Ant)",
    )
    tournament_size: int = Field(3, ge=1, description="individuals drawn per selection tournament (PDERL: 3)")
    mini_buffer_size: int = Field(
        50_000, gt=0, description="states kept per individual (its 'mini buffer', paper: 50,000)"
    )
    eval_episodes: int = Field(
        1, ge=1, description="episodes per individual per generation; fitness is their mean return (PDERL code: 1)"
    )
    mutation_prob: float = Field(0.9, ge=0, le=1, description="chance that a non-elite is mutated (PDERL: 0.9)")
    mutation_std: float = Field(0.05, ge=0, description="std of the Gaussian weight noise before scaling (PDERL: 0.05)")
    mutation_states: int = Field(
        256,
        ge=1,
        description="states from the individual's mini buffer the action sensitivity is measured on (PDERL: 256)",
    )
    mutation_min_sensitivity: float = Field(
        0.01, gt=0, description="sensitivities below this are raised to it before dividing (PDERL: 0.01)"
    )
    crossover_transitions: int = Field(
        4_000,
        ge=1,
        description="latest states taken from each parent's mini buffer to distil the child on (PDERL: 4,000)",
    )
    crossover_epochs: int = Field(12, ge=1, description="passes over the child's distillation states (PDERL: 12)")
    crossover_batch_size: int = Field(128, ge=1, description="minibatch of the distillation (PDERL: 128)")
    crossover_lr: float = Field(1e-3, gt=0, le=1, description="Adam learning rate of the distillation (PDERL: 1e-3)")
    crossover_action_penalty: float = Field(
        1 / 128,
        ge=0,
        description="weight of mean(a^2) beside the summed squared action error (per row); 1/128 is PDERL's "
        "sum-over-batch loss plus mean(a^2) at batch 128, rescaled",
    )
    rl_sync_period: int = Field(
        1,
        ge=1,
        description="every this many generations the RL actor replaces the worst individual "
        "(PDERL code: 1 on Hopper, Walker2d, Ant; 10 elsewhere)",
    )
    checkpoint_every: int = Field(
        5, ge=1, description="generations between resumable checkpoints (OUT/obj{K}/pderl_state.pt)"
    )
    device: Literal["auto", "cpu", "cuda"] = Field("auto", description="'auto' picks cuda when present")
    precision: PrecisionChoice = precision_field(
        "the RL agent's TD3 updates (the population's episodes and evolution stay fp32)"
    )

    @model_validator(mode="after")
    def _consistent(self) -> "TrainPderlParams":
        if n_elites(self.elite_fraction, self.population_size) >= self.population_size:
            raise ValueError(
                f"elite_fraction {self.elite_fraction} of population_size {self.population_size} leaves no "
                "individual to evolve"
            )
        if self.crossover_transitions > self.mini_buffer_size:
            raise ValueError(
                f"crossover_transitions ({self.crossover_transitions}) must be <= mini_buffer_size ({self.mini_buffer_size})"
            )
        if self.mutation_states > self.mini_buffer_size:
            raise ValueError(
                f"mutation_states ({self.mutation_states}) must be <= mini_buffer_size ({self.mini_buffer_size})"
            )
        return self
