"""Every params section's model, in one place (for whole-file checks: presets, sweep cells).

Kept out of pipeline/params/__init__.py on purpose: a stage imports only its own section's
model, so its DVC code deps (its import closure) do not include the others', and editing one
stage's params model reruns only that stage. The sections and their models are the table
SECTION_MODELS of pipeline/params/__init__.py; this imports them.
"""

from __future__ import annotations

import importlib

from pydantic import BaseModel

from pipeline.params import SECTION_MODELS, EnvParams, RunParams


def section_models() -> dict[str, type[BaseModel]]:
    """Every params section's model: "env", "" (the top-level lists) and each stage section."""
    models: dict[str, type[BaseModel]] = {"env": EnvParams, "": RunParams}
    for name, where in SECTION_MODELS.items():
        module, cls = where.split(":")
        models[name] = getattr(importlib.import_module(f"pipeline.params.{module}"), cls)
    return models
