"""Section `interpolate`: the weight-space interpolation baseline (pipeline/baselines/interpolate.py).

A baseline the paper does not have. Left at null, both keys follow the MAPEX run the baseline is
compared with (section `extract`): as many policies as that run makes children, each evaluated
on as many episodes as a child is. Stage interpolate lists those extract keys in dvc.yaml
(INTERPOLATE_EXTRACT_KEYS), so changing extract.beta, say, leaves it up to date.
"""

from __future__ import annotations

from pydantic import Field

from pipeline.params.common import Strict

# The extract keys stage interpolate reads (dvc.yaml lists each; `mapex sync-params` fills them in).
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
