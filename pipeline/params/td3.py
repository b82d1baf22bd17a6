"""Section `td3`: the TD3 agent, read by every stage that builds one.

The paper's appendix gives one table, "PDERL and TD3 hyperparameters", shared by the TD3
specialists (`train_specialist`), the RL agent inside PDERL (`train_pderl`) and the RL agents
of MOPDERL's phase 2 (`mopderl`). Those three stages read this section; each keeps its own
budget and run settings in its own section. So changing a specialist run's length
(`train_specialist.total_steps`) or its keep-best schedule reruns the TD3 specialists only,
while a change here reruns every stage that trains a TD3 agent, as it must.

Defaults are the paper's table. Which stage reads which key: every key is read by
`train_specialist` and `train_pderl`; `mopderl` reads all but `learning_starts`,
`hidden_sizes` and `secondary_critics` (its agents start from PDERL's filled buffers and
networks), which cannot change without PDERL's specialists, its inputs, changing too.
`shared_init` and `shared_prefix_steps` / `shared_prefix_weights` (not in the paper) are read by
`train_specialist` only.
"""

from __future__ import annotations

from pydantic import Field, model_serializer, model_validator

from pipeline.params.common import Strict


class TD3Params(Strict):
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
    cuda_graphs: bool = Field(True, description="on CUDA, replay each update as captured CUDA graphs (false: eager)")
    shared_init: bool = Field(
        False,
        description="every objective's TD3 specialist of a seed starts from the same initial actor and critic weights "
        "(objective 0's; exploration, replay and noise streams stay per objective), so that weight-space interpolation "
        "between them (stage interpolate) has a chance; not in the paper (independent inits). train_specialist only: "
        "PDERL's and MOPDERL's agents ignore it",
    )

    shared_prefix_steps: int = Field(
        0,
        ge=0,
        description="the TD3 specialists of a seed fork from one TD3 trained this many env steps on a mixed reward "
        "(shared_prefix_weights), each then training on its own objective to train_specialist.total_steps: "
        "its networks, critics, optimizer moments and replay rows are every specialist's first steps (a seed "
        "takes shared_prefix_steps + n x (total_steps - shared_prefix_steps) env frames); for weight-space "
        "interpolation (Frankle et al. 2020: networks that share early training are linearly connected); "
        "needs secondary_critics; 0: independent specialists, as in the paper. train_specialist only",
    )
    shared_prefix_weights: list[float] | None = Field(
        None,
        description="weights of the shared prefix's mixed reward, one per objective, applied to the env's rewards "
        "as they are (default: equal, 1/n each)",
    )

    @model_serializer(mode="wrap")
    def _dump(self, handler):
        # shared_init off and no shared prefix (the defaults) are left out of the dump: the
        # specialists' metadata and run fingerprints record the section as it was before the keys
        # existed, so their bits stay the same
        out = handler(self)
        if isinstance(out, dict):
            if not self.shared_init:
                out.pop("shared_init", None)
            if not self.shared_prefix_steps:
                out.pop("shared_prefix_steps", None)
            if self.shared_prefix_weights is None:
                out.pop("shared_prefix_weights", None)
        return out

    @model_validator(mode="after")
    def _consistent(self) -> "TD3Params":
        if any(h <= 0 for h in self.hidden_sizes):
            raise ValueError(f"hidden_sizes must be positive, got {self.hidden_sizes}")
        if self.shared_prefix_steps and not self.secondary_critics:
            raise ValueError(
                f"shared_prefix_steps ({self.shared_prefix_steps}) needs secondary_critics: true (each specialist "
                "takes the prefix's critic of its own objective)"
            )
        if self.shared_prefix_weights is not None and (
            not self.shared_prefix_weights or any(w < 0 for w in self.shared_prefix_weights)
        ):
            raise ValueError(f"shared_prefix_weights must be non-negative weights, got {self.shared_prefix_weights}")
        if self.learning_starts < self.batch_size:
            raise ValueError(f"learning_starts ({self.learning_starts}) must be >= batch_size ({self.batch_size})")
        return self


# The keys the TD3 agents of PDERL (train_pderl) and MOPDERL (mopderl) read: every key but
# shared_init, which only the TD3 specialists (train_specialist) read. Their dvc.yaml stages list
# these one by one (tests/test_dvc_deps.py checks it), so switching shared_init reruns the TD3
# specialists and nothing of PDERL or MOPDERL; `mapex plan` names them in params.yaml
# (DVC refuses a listed key that is missing from the file).
SPECIALIST_ONLY_KEYS = ("shared_init", "shared_prefix_steps", "shared_prefix_weights")
AGENT_KEYS = tuple(k for k in TD3Params.model_fields if k not in SPECIALIST_ONLY_KEYS)
