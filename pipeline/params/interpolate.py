"""Section `interpolate`: the weight-space interpolation baseline (pipeline/baselines/interpolate.py).

A baseline the paper does not have. Left at null, both keys follow the MAPEX run the baseline is
compared with (section `extract`): as many policies as that run makes children, each evaluated
on as many episodes as a child is. Stage interpolate lists those extract keys in dvc.yaml
(INTERPOLATE_EXTRACT_KEYS), so changing extract.beta, say, leaves it up to date.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from pipeline.params.common import Strict

# The extract keys stage interpolate reads (dvc.yaml lists each; `mapex plan` fills them in).
INTERPOLATE_EXTRACT_KEYS = ("iterations", "children_per_iteration", "eval_episodes")


class InterpolateParams(Strict):
    policies: int | None = Field(
        None,
        ge=0,
        description="interpolated policies per run (a simplex grid of at most this many points for N >= 3); "
        "null = the children of the MAPEX run: extract.iterations x extract.children_per_iteration",
    )
    eval_episodes: int | None = Field(
        None, gt=0, description="evaluation episodes per policy; null = extract.eval_episodes (as each child)"
    )
    align: Literal["none", "weights"] = Field(
        "none",
        description="put the specialists' hidden units in correspondence before mixing: none, or weights "
        "(Git Re-Basin's weight matching, data-free; pipeline/core/alignment.py). Issue 61; not in the paper",
    )
    repair: bool = Field(
        False,
        description="REPAIR: rescale each mixed policy's hidden preactivations to the weighted mean of the "
        "specialists' statistics on interpolate.states states from their buffers",
    )
    mix: Literal["linear", "regmean"] = Field(
        "linear",
        description="how a layer is mixed: linear (sum_i w_i theta_i) or regmean (the least-squares merge of "
        "the layers on their inputs for interpolate.states buffer states)",
    )
    regmean_alpha: float = Field(
        0.9,
        ge=0,
        le=1,
        description="RegMean's scale of the Gram matrices' off-diagonal entries (1: plain least squares)",
    )
    states: int = Field(
        4096,
        gt=0,
        description="states REPAIR and RegMean measure on, drawn in equal shares from the specialists' buffers "
        "(read only when repair or mix: regmean)",
    )
