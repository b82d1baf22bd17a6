"""Shared params sections: the environment and the top-level lists (seeds, methods, ...)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator


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


# Extraction variants (stage extract --variant): what each changes in section `extract`.
EXTRACT_VARIANTS = ("mapex", "mapex_posthoc", "warmup_only")
# The variants that read the critics trained jointly with the specialists (stage extract,
# list extract_variants). mapex_posthoc reads critics fitted post hoc and has its own stage
# (extract_posthoc, list posthoc_from), so that extraction with joint critics does not depend
# on post-hoc critics: DVC deps cannot depend on a matrix value.
JOINT_VARIANTS = ("mapex", "warmup_only")
# Kinds of specialists extraction can start from: td3 (stage train_specialist) and pderl
# (stage train_pderl), under data/specialists/<kind>/seedS.
SPECIALIST_KINDS = ("td3", "pderl")
BASELINES = ("mopderl", "morld")


def method_name(variant: str, kind: str) -> str:
    """The method an extraction variant from one kind of specialists is: mapex_td3, mapex_posthoc_pderl, ..."""
    return f"{variant}_{kind}"


class RunParams(Strict):
    """The top-level lists dvc.yaml fans stages out over, checked to agree with each other.

    DVC cannot filter a matrix, so each producing stage has its own list, and `methods` (what
    evaluate, score and report compare) must be exactly what those lists produce: every
    extraction variant from every kind in `extract_from` (named variant_kind), mapex_posthoc
    from every kind in `posthoc_from`, plus each baseline whose seed list is not empty. The
    check names the list to change.
    """

    seeds: list[int] = Field([0], min_length=1, description="run seeds; each seed is one independent run of every method")
    objectives: list[int] = Field([0, 1], min_length=1, description="objective indices, one specialist each")
    pderl_seeds: list[int] = Field(
        [], description="seeds of stage train_pderl (PDERL specialists): [] or the same list as `seeds`"
    )
    extract_from: list[Literal["td3", "pderl"]] = Field(
        ["td3"], min_length=1, description="kinds of specialists the extract stage starts from (td3, pderl)"
    )
    extract_variants: list[str] = Field(
        ["mapex", "warmup_only"], description="extraction variants run from each kind in extract_from, with the specialists' "
        "joint critics: mapex, warmup_only (the ablation: no advantage-weighted phase)"
    )
    posthoc_from: list[Literal["td3", "pderl"]] = Field(
        [], description="kinds of specialists to fit post-hoc critics for (stage fit_critics) and run MAPEX-PostHoc "
        "from (stage extract_posthoc, method mapex_posthoc_<kind>); [] skips both"
    )
    mopderl_seeds: list[int] = Field([], description="seeds of the MOPDERL baseline (stage mopderl): [] or `seeds`")
    morld_seeds: list[int] = Field([], description="seeds of the MORL/D baseline (stage morld): [] or `seeds`")
    methods: list[str] = Field(
        ["mapex_td3", "warmup_only_td3"], min_length=1,
        description="what evaluate, score and report compare, one data/fronts/<method>/seedS each: <variant>_<kind> for "
        "each extraction variant and kind, plus mopderl and morld when their seed lists are set",
    )

    @field_validator("seeds", "objectives", "pderl_seeds", "mopderl_seeds", "morld_seeds")
    @classmethod
    def _unique_non_negative(cls, v: list[int]) -> list[int]:
        if len(set(v)) != len(v):
            raise ValueError(f"entries must be unique, got {v}")
        if any(x < 0 for x in v):
            raise ValueError(f"entries must be >= 0, got {v}")
        return v

    @field_validator("extract_from", "extract_variants", "posthoc_from", "methods")
    @classmethod
    def _unique(cls, v: list[str]) -> list[str]:
        if len(set(v)) != len(v):
            raise ValueError(f"entries must be unique, got {v}")
        return v

    @field_validator("extract_variants")
    @classmethod
    def _joint_variants(cls, v: list[str]) -> list[str]:
        if "mapex_posthoc" in v:
            raise ValueError("mapex_posthoc is chosen by `posthoc_from` (the kinds of specialists to fit post-hoc critics "
                             "for, e.g. [td3]), not by extract_variants; remove it here")
        bad = [x for x in v if x not in JOINT_VARIANTS]
        if bad:
            raise ValueError(f"unknown variants {bad}: expected entries of {list(JOINT_VARIANTS)}")
        return v

    def produced_methods(self) -> list[str]:
        """The methods the producer lists make."""
        out = [method_name(v, k) for k in self.extract_from for v in self.extract_variants]
        out += [method_name("mapex_posthoc", k) for k in self.posthoc_from]
        return out + [b for b, seeds in (("mopderl", self.mopderl_seeds), ("morld", self.morld_seeds)) if seeds]

    @model_validator(mode="after")
    def _consistent(self) -> "RunParams":
        for key in ("pderl_seeds", "mopderl_seeds", "morld_seeds"):
            v = getattr(self, key)
            if v and sorted(v) != sorted(self.seeds):
                raise ValueError(f"{key} = {v}: must be [] or the same seeds as `seeds` ({self.seeds}), since every method "
                                 f"is evaluated on every seed")
        needs_pderl = [m for m in ("pderl" in self.extract_from and "extract_from: pderl",
                                   "pderl" in self.posthoc_from and "posthoc_from: pderl",
                                   self.mopderl_seeds and "mopderl_seeds") if m]
        if needs_pderl and not self.pderl_seeds:
            raise ValueError(f"{' and '.join(needs_pderl)}: PDERL specialists are needed; set pderl_seeds to {self.seeds}")
        produced = self.produced_methods()
        if sorted(self.methods) != sorted(produced):
            raise ValueError(f"methods = {self.methods}, but extract_from x extract_variants, posthoc_from and the baselines' seed lists "
                             f"produce {produced}: set methods to that list (or change those lists)")
        return self
