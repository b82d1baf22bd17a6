"""Section `critic_fidelity`: how critics are compared with Monte-Carlo returns of their buffer.

Read by stage `critic_fidelity` (joint critics) and by stage `fit_critics` (post-hoc critics),
so both kinds of critic are scored on exactly the same states by the same rule.
"""

from __future__ import annotations

from pydantic import Field

from pipeline.params.common import Strict


class CriticFidelityParams(Strict):
    episodes: int = Field(
        10, gt=0, description="score the last this-many episodes of the buffer (closest to the final policy)"
    )
    tail_tolerance: float = Field(
        0.01,
        gt=0,
        lt=1,
        description="in a cut (truncated or unfinished) episode keep only states whose missing tail weight gamma^H is <= this",
    )
