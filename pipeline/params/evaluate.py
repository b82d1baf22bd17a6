"""Section `evaluate`: the final re-evaluation of every member of an extracted population.

The paper evaluates each actor on 5 episodes during extraction; a lucky evaluation can keep a
child on the front for good, so the final front is measured again on fresh episode seeds with
more episodes. Only what changes the episodes lives here: scoring them (front metrics) is the
`score` stage's, so a change to a metric's setting never reruns an episode.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from pipeline.params.common import PrecisionChoice, Strict, precision_field


class EvaluateParams(Strict):
    episodes: int = Field(10, ge=1, le=1000, description="episodes per member on fresh seeds (extraction uses 5)")
    seed_stream: int = Field(
        1, ge=1, description="eval_seeds stream; extraction evaluates on stream 0, so >= 1 gives unseen episodes"
    )
    device: Literal["auto", "cpu", "cuda"] = Field(
        "cpu", description="where the actors run; small MLPs stepped one env step at a time are fastest on cpu"
    )
    processes: int = Field(
        1,
        ge=1,
        le=256,
        description="worker processes the members are dealt to (round robin), side by side, each with "
        "MAPEX_TORCH_THREADS threads; on a CPU with one torch thread they are forked (no imports to pay). A member's "
        "episodes are the same whatever the count, so this changes no artifact; on CUDA the members run in the "
        "stage's own process",
    )
    precision: PrecisionChoice = precision_field(
        "the actors' forward passes in the episodes (the project's own MLPs; imported TorchScript or torch.export "
        "policies run in fp32)",
        auto="fp32 (a forward of a few rows per env step measured no faster in bf16)",
    )
