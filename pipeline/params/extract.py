"""Section `extract`: MAPEX extraction (paper Algorithm 1 and its appendix tables).

`epochs`, `beta` and `omega_max` left at null take the paper's per-environment values
(appendix table "Environment-specific MAPEX hyperparameters", in presets/envs.yaml: `paper_extract`); the other defaults are the
paper's shared MAPEX table, or the precursor code's value where the paper gives none.
Two settings deviate from the paper and say so in their descriptions: `advantage_norm: none`,
the default (a mix of units, see pipeline/extraction/mapex.py), and `children_per_iteration` above 1
(K children per iteration from the same front, trained together). Five more are not in the paper
and off by default (EXTENSION_KEYS): the hybrid extraction (`init`, `warmup_after_interpolate`,
`seed_interpolation`) and early stopping (`stop_patience`, `stop_min_gain`).
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from pipeline.params.common import PrecisionChoice, Strict, precision_field
from pipeline.params.env_facts import paper_extract, paper_extract_envs


class ExtractParams(Strict):
    iterations: int = Field(
        1200,
        ge=0,
        description="iterations of Algorithm 1, each adding children_per_iteration children (paper: 1,200 of 1)",
    )
    children_per_iteration: int = Field(
        1,
        ge=1,
        description="K children per iteration, trained together as one stacked ensemble; 1 = Algorithm 1. K > 1 is a "
        "deviation: all K draw their parents by the same roulette from the front at the start of the iteration (siblings "
        "never see each other), each with its own hybrid buffer and RNG streams; the run makes iterations x K children",
    )
    child_buffer_size: int = Field(200_000, gt=0, description="rows of each child's hybrid buffer (paper: 200,000)")
    eval_episodes: int = Field(5, gt=0, description="evaluation episodes per policy (paper: 5)")
    warmup_steps: int = Field(
        1000, ge=0, description="gradient steps regressing onto the mean parent action (paper: 1,000)"
    )
    warmup_lr: float = Field(3e-4, gt=0, le=1, description="Adam learning rate of the warm-up (paper: 3e-4)")
    warmup_batch_size: int = Field(256, gt=0, description="minibatch of the warm-up (paper: 256)")
    epochs: int | None = Field(
        None, ge=0, description="passes over the hybrid buffer; null = the paper's value for env.id"
    )
    beta: float | None = Field(None, gt=0, description="AWR temperature; null = the paper's value for env.id")
    omega_max: float | None = Field(
        None, gt=0, description="clip of the AWR weight; null = the paper's value for env.id"
    )
    lr: float = Field(3e-4, gt=0, le=1, description="Adam learning rate of the weighted regression (precursor: 3e-4)")
    batch_size: int = Field(256, gt=0, description="minibatch of the weighted regression (precursor: 256)")
    max_grad_norm: float | None = Field(
        None, gt=0, description="clip the child's gradient norm (precursor: 1.0); null = off"
    )
    hidden_sizes: list[Annotated[int, Field(gt=0)]] = Field(
        [256, 256], min_length=1, description="hidden widths of each child policy (positive)"
    )
    weight_norm: Literal["l2", "l1"] = Field(
        "l2", description="target weight = centroid / its L2 norm (paper) or L1 sum (precursor)"
    )
    advantage_recompute: Literal["every_step", "once"] = Field(
        "every_step", description="Q(s, pi_new(s)) at every step (Algorithm 1) or once after warm-up (precursor)"
    )
    advantage_norm: Literal["none", "zscore", "objective_range"] = Field(
        "none",
        description="none: raw advantages mixed with a weight from range-normalised returns (a deviation: neither the "
        "paper, whose returns are raw too, nor consistent units; the default only because every measurement so far used "
        "it); objective_range: each A_m divided by objective m's population range (the units of w); zscore of A_mixed (precursor)",
    )
    facet_bridge_ratio: float | None = Field(
        3.0,
        gt=1,
        description="N >= 3 objectives only (an extension: the paper defines gaps for N = 2; docs/n_objectives.md): "
        "the roulette draws only from gaps on the front's surface; a facet reached from outside the front mesh through "
        "an edge whose ends the mesh's boundary joins in steps shorter than 1/ratio of it is left out, and the steps "
        "along a thin front become 2-parent gaps; null = every facet of the mesh (the rule before). N = 2 never reads it",
    )
    # ---- the hybrid extraction (not in the paper; docs/manual.md, "Hybrid extraction") and early stopping
    init: Literal["warmup", "interpolate"] = Field(
        "warmup",
        description="how a child starts: warmup = a fresh random network warmed up on the mean parent action (the "
        "paper); interpolate = its parents' weights mixed with equal coefficients 1/N (the point of the parents' "
        "simplex that the target weight points at), where the parents are plain actors of the children's "
        "hidden_sizes and action bounds, else the paper's warm-up (a fallback, counted in the report); not in the paper",
    )
    warmup_after_interpolate: bool = Field(
        False,
        description="init interpolate only: also run the warm-up (warmup_steps onto the mean parent action) from the "
        "interpolated start; false = straight to the advantage-weighted phase",
    )
    seed_interpolation: int = Field(
        0,
        ge=0,
        description="seed the population, after the starting policies, with the policies of the interpolation "
        "baseline's grid of at most this many points between the specialists (evaluated like any member, origin "
        "'interpolated'), so gap selection sends children into the gaps interpolation leaves; 0 = off (the paper); "
        "skipped, and recorded, where the specialists cannot be mixed",
    )
    # how init interpolate's starts and seed_interpolation's grid are mixed: the options of stage
    # interpolate (section interpolate; pipeline/core/alignment.py, issue 61), one implementation
    align: Literal["none", "weights"] = Field(
        "none",
        description="init interpolate and seed_interpolation: put the mixed actors' hidden units in correspondence "
        "first (weights = Git Re-Basin's weight matching); as interpolate.align; not in the paper",
    )
    repair: bool = Field(
        False,
        description="init interpolate and seed_interpolation: REPAIR each mix on mix_states states (a child's: its "
        "hybrid buffer's first rows; a seed's: the specialists' buffers); as interpolate.repair",
    )
    mix: Literal["linear", "regmean"] = Field(
        "linear", description="init interpolate and seed_interpolation: linear or regmean mixing; as interpolate.mix"
    )
    regmean_alpha: float = Field(0.9, ge=0, le=1, description="mix regmean: as interpolate.regmean_alpha")
    mix_states: int = Field(
        4096, gt=0, description="repair or mix regmean: the states they measure on; as interpolate.states"
    )
    stop_patience: int = Field(
        0,
        ge=0,
        description="stop the extraction early once its hypervolume (extraction-time returns, scaled by the starting "
        "policies' range, reference at their minimum) has risen by at most stop_min_gain over this many iterations; "
        "0 = off (the paper: every iteration runs)",
    )
    stop_min_gain: float = Field(
        0.01,
        ge=0,
        description="stop_patience > 0: the relative rise of that hypervolume over stop_patience iterations below "
        "which the run stops (0.01 = 1%)",
    )
    device: Literal["auto", "cpu", "cuda"] = Field("auto", description="'auto' picks cuda when present")
    precision: PrecisionChoice = precision_field(
        "the children's training (their warm-up and advantage-weighted regression, the critics and parents they "
        "read); the evaluation episodes stay fp32",
        auto="bf16 where the hardware has bfloat16 natively and the child's hidden width is >= 256, else fp32",
    )

    def resolved(self, env_id: str) -> "ExtractParams":
        """A copy with epochs, beta and omega_max filled from the paper's table for `env_id`
        (presets/envs.yaml, `paper_extract`)."""
        missing = [k for k in ("epochs", "beta", "omega_max") if getattr(self, k) is None]
        defaults = paper_extract(env_id) if missing else None
        if missing and defaults is None:
            raise ValueError(
                f"extract.{missing[0]} is null but env {env_id!r} has no paper values (presets/envs.yaml, "
                f"paper_extract); set it explicitly (the paper has values for {paper_extract_envs()})"
            )
        fill = dict(zip(("epochs", "beta", "omega_max"), defaults or (None, None, None)))
        return self.model_copy(update={k: fill[k] for k in missing})


# The advantage-weighted phase's keys. The warm-up-only ablation (epochs = 0) reads none of them,
# so its dvc.yaml stage (warmup_only) lists only WARMUP_ONLY_KEYS: changing extract.beta, say,
# leaves every warm-up-only front up to date. A test checks dvc.yaml against this list.
AWR_KEYS = ("epochs", "beta", "omega_max", "lr", "batch_size", "max_grad_norm", "advantage_recompute", "advantage_norm")
# The hybrid extraction's and early stopping's keys (not in the paper). The warm-up-only ablation
# reads none of them either (variant_config sets them to their defaults), and a run whose keys are
# at their defaults records none of them (`without_default_extensions`), so that its artifacts and
# resume fingerprint are byte for byte those from before the keys existed.
MIXING_KEYS = ("align", "repair", "mix", "regmean_alpha", "mix_states")
EXTENSION_KEYS = (
    "init",
    "warmup_after_interpolate",
    "seed_interpolation",
    "stop_patience",
    "stop_min_gain",
    *MIXING_KEYS,
)
WARMUP_ONLY_KEYS = tuple(k for k in ExtractParams.model_fields if k not in AWR_KEYS + EXTENSION_KEYS)


def without_default_extensions(dump: dict) -> dict:
    """An `extract` model_dump without the EXTENSION_KEYS that are off or not read: the switches
    init, seed_interpolation and stop_patience where at their defaults (off), and
    warmup_after_interpolate (read only with init interpolate) and stop_min_gain (only with
    stop_patience > 0) where their switch is off. With every extension off, the record of a run
    is what it was before they existed."""
    fields = ExtractParams.model_fields
    on = {
        k: dump.get(k, fields[k].default) != fields[k].default for k in ("init", "seed_interpolation", "stop_patience")
    }
    mixing = {k: dump.get(k, fields[k].default) != fields[k].default for k in MIXING_KEYS}
    keep = on | mixing | {"warmup_after_interpolate": on["init"], "stop_min_gain": on["stop_patience"]}
    return {k: v for k, v in dump.items() if k not in EXTENSION_KEYS or keep[k]}
