"""Section `morld`: the MORL/D baseline (morl-baselines 1.3.0, stage morld).

MORL/D (Felten, Talbi & Danoy, 2024) trains a population of MOSAC agents, each on a
weighted-sum scalarisation of the reward, turn by turn: the selected agent collects
`exchange_every` env frames (one SAC update per frame), the others then make
`update_passes` updates each, every agent is evaluated and the Pareto archive updated, and
the weights are adapted (PSA). The paper ran the library's MORLD with scalarization "ws",
evaluation "ser", policy MOSAC, population 6, exchange every 50,000 frames, a shared replay
buffer, PSA weight adaptation and gamma 0.99, for 4M frames (Swimmer 2M); those are the
defaults here. The MOSAC values are the library's own defaults (the paper changes none).
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from pipeline.params.common import Strict


class MorldParams(Strict):
    total_frames: int = Field(
        4_000_000,
        gt=0,
        description="training env frames (paper: 4,000,000; Swimmer 2,000,000). Spent in whole exchanges of "
        "exchange_every frames, so a budget that is not a multiple is rounded up, as MORL/D does. MORL/D's own "
        "archive evaluations and our final evaluation are not counted (both are reported separately)",
    )
    pop_size: int = Field(6, ge=2, description="MOSAC agents, one weight vector each (paper: 6)")
    exchange_every: int = Field(50_000, gt=0, description="frames one agent collects per turn (paper: 50,000)")
    shared_buffer: bool = Field(True, description="one replay buffer shared by every agent (paper: true)")
    weight_adaptation: Literal["PSA"] | None = Field(
        "PSA", description="weight adaptation after each exchange: PSA (paper) or null (fixed weights)"
    )
    weight_init: Literal["uniform", "random"] = Field(
        "uniform", description="initial weights: uniform (equally spaced on the simplex; library default) or random"
    )
    scalarization: Literal["ws"] = Field(
        "ws",
        description="weighted sum (paper). The library's Tchebycheff keeps its reference point in a closure, "
        "which a checkpoint cannot hold, so it is not offered",
    )
    evaluation_mode: Literal["ser", "esr"] = Field(
        "ser", description="how MORL/D scores its agents for its archive (paper: ser)"
    )
    gamma: float = Field(
        0.99, gt=0, le=1, description="discount of MOSAC and of MORL/D's archive returns (paper: 0.99)"
    )
    neighborhood_size: int = Field(
        1, ge=0, description="neighbours per weight vector (library default 1; used by sharing)"
    )
    update_passes: int = Field(
        10, ge=0, description="after each turn, updates made by every other agent on the (shared) buffer (library: 10)"
    )
    front_eval_episodes: int = Field(
        5,
        ge=1,
        description="MORL/D's archive evaluation: calls per agent per exchange, each averaging 5 stochastic episodes "
        "(library default 5, i.e. 25 episodes). Its discounted returns only decide what the archive keeps",
    )
    # MOSAC (library defaults)
    hidden_sizes: list[int] = Field(
        [256, 256], min_length=1, description="MOSAC actor and critic hidden widths (library default [256, 256])"
    )
    batch_size: int = Field(128, gt=0, description="MOSAC minibatch (library default 128)")
    learning_starts: int = Field(
        1_000,
        ge=0,
        description="frames of uniform random actions before the first agent's updates start (library: 1,000)",
    )
    buffer_size: int = Field(1_000_000, gt=0, description="replay buffer rows (library default 1,000,000)")
    policy_lr: float = Field(3e-4, gt=0, description="MOSAC actor learning rate (library default 3e-4)")
    q_lr: float = Field(1e-3, gt=0, description="MOSAC critic and temperature learning rate (library default 1e-3)")
    tau: float = Field(0.005, gt=0, le=1, description="target network soft-update rate (library default 0.005)")
    policy_freq: int = Field(2, ge=1, description="actor updated every this many steps, this many times (library: 2)")
    target_net_freq: int = Field(1, ge=1, description="target networks updated every this many steps (library: 1)")
    alpha: float = Field(0.2, gt=0, description="entropy coefficient when autotune is off (library default 0.2)")
    autotune: bool = Field(True, description="tune the entropy coefficient automatically (library default true)")
    # ours
    eval_episodes: int = Field(
        5,
        ge=1,
        description="deterministic episodes per exported actor (tanh of the mean action); their mean undiscounted "
        "return is the member's `returns` in population.pt (MAPEX's extraction: 5)",
    )
    checkpoint_every: int = Field(
        1, ge=1, description="exchanges between resumable checkpoints (OUT/morld_state.pt, replay buffer included)"
    )
    device: Literal["auto", "cpu", "cuda"] = Field("auto", description="'auto' picks cuda when present")

    @model_validator(mode="after")
    def _consistent(self) -> "MorldParams":
        if self.neighborhood_size >= self.pop_size:
            raise ValueError(f"neighborhood_size ({self.neighborhood_size}) must be < pop_size ({self.pop_size})")
        if self.batch_size > self.buffer_size:
            raise ValueError(f"batch_size ({self.batch_size}) must be <= buffer_size ({self.buffer_size})")
        if any(h <= 0 for h in self.hidden_sizes):
            raise ValueError(f"hidden_sizes must be positive, got {self.hidden_sizes}")
        return self

    def frames(self) -> int:
        """Training frames the run spends: total_frames rounded up to whole exchanges."""
        return -(-self.total_frames // self.exchange_every) * self.exchange_every
