"""Section `score`: how the re-evaluated returns are scored (pipeline.evaluation.metrics).

Scoring is arithmetic on the evaluate stage's returns, so these settings (and
env.reference_point, which score reads from the `env` section) rerun no episode.
"""

from __future__ import annotations

from pydantic import Field

from pipeline.params.common import Strict


class ScoreParams(Strict):
    distinct_tol: float = Field(
        0.02, gt=0, le=1, description="distinct_count merge radius, as a fraction of the [reference, ideal] box side"
    )
    utility_weights: int = Field(100, ge=2, le=100_000, description="evenly spread weight vectors for expected utility")
