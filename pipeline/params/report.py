"""Section `report`: how the report stage draws its figures, decides its verdict and flags weak
specialists (pipeline/reporting/specialists.py has the rule)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, field_validator

from pipeline.params.common import Strict


class ReportParams(Strict):
    dpi: int = Field(120, ge=50, le=600, description="resolution of the raster figures")
    formats: list[Literal["png", "svg", "pdf"]] = Field(
        ["png"], min_length=1, description="figure file formats; png is required (report.md embeds it)"
    )
    figure_width: float = Field(11.0, gt=2, le=40, description="width of a figure in inches")
    min_difference: float = Field(
        0.05,
        ge=0,
        lt=1,
        description="with one seed, the relative hypervolume difference below which the verdict is a tie",
    )
    noise_sems: float = Field(
        2.0,
        gt=0,
        le=10,
        description="with >= 2 seeds, how many SEMs the mean paired hypervolume difference must exceed to count",
    )
    pairs: list[Annotated[list[str], Field(min_length=2, max_length=2)]] | None = Field(
        None,
        description="the pairs of methods the verdicts compare, [a, b] each ('a beat, lost to or tied with b'), "
        "by their names in methods (variants too); null: the usual pairs (pipeline/reporting/verdicts.py "
        "VERDICT_PAIRS) and each method variant against the method it varies",
    )
    weak_specialist_fraction: float | None = Field(
        0.5,
        gt=0,
        le=1,
        description="warn when a specialist's own-objective return is below this fraction of its kind's best seed's "
        "(of the way up from the worst starting policy where that best is <= 0); null = off",
    )
    weak_specialist_min_return: list[Annotated[float, Field(allow_inf_nan=False)] | None] | None = Field(
        None,
        min_length=1,
        description="warn when a specialist's own-objective return is below this value, one per objective "
        "(null = unused)",
    )

    @field_validator("formats")
    @classmethod
    def _png_and_unique(cls, v: list[str]) -> list[str]:
        if "png" not in v:
            raise ValueError(f"must include 'png' (report.md embeds the PNG figures), got {v}")
        if len(set(v)) != len(v):
            raise ValueError(f"entries must be unique, got {v}")
        return v
