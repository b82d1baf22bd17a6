"""Section `export`: which methods' fronts stage export writes as self-contained policy files.

Off by default (`methods: []`): the stage runs one item per seed and listed method. `mapex
export` itself exports any population on demand (docs/import_export.md).
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator

from pipeline.params.common import Strict


class ExportParams(Strict):
    methods: list[str] = Field(
        [], description="methods whose fronts stage export writes (each must be in `methods`); [] = the stage is off"
    )
    onnx: Literal["auto", "yes", "no"] = Field(
        "auto", description="also write ONNX files: auto = where the onnx package is installed; yes = required"
    )

    @field_validator("methods")
    @classmethod
    def _unique(cls, v: list[str]) -> list[str]:
        if len(set(v)) != len(v):
            raise ValueError(f"entries must be unique, got {v}")
        return v
