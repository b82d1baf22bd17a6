"""Shared params sections: the environment and the run's seeds/objectives lists."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, field_validator


class Strict(BaseModel):
    """Base for every params model: unknown keys are errors, values are frozen."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class EnvParams(Strict):
    """Section `env`: which MO-Gymnasium environment every stage works on."""

    id: str = Field("mo-halfcheetah-v5", description="MO-Gymnasium env id (continuous Box actions, vector reward)")
    max_episode_steps: int = Field(750, gt=0, description="episode cap; the paper uses 750 steps")
    reference_point: list[float] | None = Field(
        None, description="hypervolume reference point, one value per objective, worse than any policy scores"
    )
    objective_names: list[str] | None = Field(None, description="axis labels for the objectives (optional)")


class RunParams(Strict):
    """Top-level `seeds`, `objectives` and `pderl_seeds`: the lists dvc.yaml fans stages out over."""

    seeds: list[int] = Field([0], min_length=1, description="run seeds; each seed is one independent run")
    objectives: list[int] = Field([0, 1], min_length=1, description="objective indices, one specialist each")
    pderl_seeds: list[int] = Field(
        [], description="seeds that also train PDERL specialists (stage train_pderl; empty: none, as in the quickstart)"
    )

    @field_validator("seeds", "objectives", "pderl_seeds")
    @classmethod
    def _unique_non_negative(cls, v: list[int]) -> list[int]:
        if len(set(v)) != len(v):
            raise ValueError(f"entries must be unique, got {v}")
        if any(x < 0 for x in v):
            raise ValueError(f"entries must be >= 0, got {v}")
        return v
