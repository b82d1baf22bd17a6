"""Shared params sections: the environment and the top-level lists (seeds, methods, ...)."""

from __future__ import annotations

from typing import Any, Literal, get_args, get_origin

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, create_model, field_validator, model_validator

from pipeline.params.methods import RUN_LISTS
from pipeline.params.runlists import derived_lists


def _element(annotation: Any) -> Any:
    """The element type of a run list's annotation (list[X] or list[X] | None); None if not a list."""
    options = (
        [annotation] if get_origin(annotation) is list else [a for a in get_args(annotation) if a is not type(None)]
    )
    lists = [get_args(a)[0] for a in options if get_origin(a) is list]
    return lists[0] if lists else None


# The derived run lists the validators below check, by their element type (RUN_LISTS)
INT_LISTS = tuple(k for k, (ann, _) in RUN_LISTS.items() if _element(ann) is int)
CHOICE_LISTS = tuple(k for k, (ann, _) in RUN_LISTS.items() if get_origin(_element(ann)) is Literal)


class Strict(BaseModel):
    """Base for every params model: unknown keys are errors, values are frozen."""

    model_config = ConfigDict(extra="forbid", frozen=True)


PrecisionChoice = Literal["fp32", "bf16", "auto"]


def precision_field(
    what: str, auto: str = "bf16 where the hardware has bfloat16 natively and the hidden width is >= 256, else fp32"
):
    """The `precision` key of a section that trains or evaluates (pipeline/core/precision.py)."""
    return Field(
        "fp32",
        description=f"arithmetic of {what}: fp32; bf16 (bfloat16 matmuls; master weights, optimizer state, losses, "
        f"targets and sums in fp32); auto: {auto} (pipeline/core/precision.py). The stage records what it used in "
        "its provenance record",
    )


class RewardTerm(Strict):
    """One objective of a single-objective env, from one of its reward terms (env.reward_terms)."""

    info: str | None = Field(
        None, description="key of the info dict the env returns each step (e.g. reward_forward, reward_ctrl)"
    )
    function: str | None = Field(
        None,
        description="module:function, the user's own code, called each step as f(obs, action, reward, next_obs, info) "
        "-> float (instead of info)",
    )
    scale: float = Field(1.0, description="the term's value is multiplied by this")
    name: str | None = Field(None, description="the objective's name in the report (default: the key or function)")

    @model_validator(mode="after")
    def _one_source(self) -> "RewardTerm":
        if (self.info is None) == (self.function is None):
            raise ValueError("give exactly one of info (a key of the step's info dict) or function (module:function)")
        if self.function is not None and ":" not in self.function:
            raise ValueError(f"function = {self.function!r}: expected 'module:function'")
        return self

    @property
    def label(self) -> str:
        return self.name or self.info or str(self.function).split(":", 1)[1]


class EnvParams(Strict):
    """Section `env`: which environment every stage works on."""

    id: str = Field(
        "mo-halfcheetah-v5",
        description="env id (continuous Box actions): an MO-Gymnasium id (vector reward), a Gymnasium id, or "
        "Gymnasium's module:EnvId form (importing the module registers your env); a single-objective env needs "
        "reward_terms",
    )
    max_episode_steps: int = Field(750, gt=0, description="episode cap; the paper uses 750 steps")
    reward_terms: list[RewardTerm] | None = Field(
        None,
        min_length=2,
        description="a single-objective env's objectives, one per reward term: [{info: KEY} or {function: "
        "module:function}, with scale and name]; null: the env returns a vector reward itself (MO-Gymnasium)",
    )
    reference_point: list[float] | Literal["auto"] | None = Field(
        None,
        description="hypervolume reference point, one value per objective, worse than any policy scores; "
        "null: the env's entry in presets/envs.yaml, reference_point, or auto where it has none; auto: derived from "
        "each run's starting policies (stage score; docs/reference_points.md)",
    )
    objective_names: list[str] | None = Field(
        None, description="axis labels for the objectives (optional; default: the reward terms' names)"
    )

    @model_validator(mode="after")
    def _names_from_terms(self) -> "EnvParams":
        if self.reward_terms and self.objective_names is None:
            object.__setattr__(self, "objective_names", [t.label for t in self.reward_terms])
        if (
            self.reward_terms
            and self.objective_names is not None
            and len(self.objective_names) != len(self.reward_terms)
        ):
            raise ValueError(
                f"objective_names has {len(self.objective_names)} names, reward_terms {len(self.reward_terms)} terms"
            )
        return self


# The generated block older params files held (`mapex plan` removes it: the plan in dvc.yaml
# holds what DVC needs of the lists now, pipeline/params/plan.py).
GENERATED_BEGIN = "# --- generated from `methods` and `seeds` by `mapex sync-params`: do not edit ---"
GENERATED_END = "# --- end of generated lists ---"
# The keys a user writes among the top-level lists; RunParams' others are derived.
USER_RUN_KEYS = ("seeds", "objectives", "methods", "variants")


class _RunParams(Strict):
    """The top-level lists: what to run (`seeds`, `objectives`, `methods`, `variants`, written by
    hand) and the run lists derived from them (pipeline.params.runlists.derived_lists), which
    `pipeline.params.load_params` merges in and `mapex plan` writes into dvc.yaml's matrices (DVC
    cannot filter a matrix). Lists that disagree with `methods` are an error naming the list; lists
    left out are not checked. The derived lists' fields are declared in RUN_LISTS
    (pipeline/params/methods.py) and added below.
    """

    seeds: list[int] = Field(
        [0], min_length=1, description="run seeds; each seed is one independent run of every method"
    )
    objectives: list[int] = Field([0, 1], min_length=1, description="objective indices, one specialist each")
    methods: list[str] = Field(
        ["mapex_td3", "warmup_only_td3"],
        min_length=1,
        description="what runs and is compared, one data/fronts/<method>/seedS each: <variant>_<kind> (variants mapex, "
        "mapex_posthoc, warmup_only; kinds td3, pderl, imported), mopderl, morld, interpolate_<kind> "
        "(pipeline/params/methods.py)",
    )
    variants: dict[str, dict] | None = Field(
        None,
        description="named variants: name -> {of: <method or kind>, label, specialists, <section>: {key: value}} "
        "(pipeline/params/variants.py); methods lists the method variants that run",
    )

    @field_validator("seeds", "objectives", *INT_LISTS, check_fields=False)
    @classmethod
    def _unique_non_negative(cls, v: list[int] | None) -> list[int] | None:
        if v is None:
            return v
        if len(set(v)) != len(v):
            raise ValueError(f"entries must be unique, got {v}")
        if any(x < 0 for x in v):
            raise ValueError(f"entries must be >= 0, got {v}")
        return v

    @field_validator("methods", *CHOICE_LISTS, check_fields=False)
    @classmethod
    def _unique(cls, v: list[str] | None) -> list[str] | None:
        if v is not None and len(set(v)) != len(v):
            raise ValueError(f"entries must be unique, got {v}")
        return v

    @model_validator(mode="after")
    def _consistent(self, info: ValidationInfo) -> "_RunParams":
        # the import entries come from section import_specialists (pipeline.params.section passes them)
        context = info.context or {}
        want = derived_lists(
            self.methods,
            self.seeds,
            context.get("imports", []),
            context.get("export", []),
            self.objectives,
            self.variants,
        )
        for key, value in want.items():
            given = getattr(self, key)
            if given is None or key not in self.model_fields_set:  # left out: nothing to check
                continue
            same = given == value if isinstance(value, dict) else sorted(given, key=repr) == sorted(value, key=repr)
            if key == "pderl_seeds" and not value and sorted(given) == sorted(self.seeds):
                same = True  # PDERL specialists no method reads may still be trained
            if not same:
                raise ValueError(
                    f"{key} = {given}, but methods {self.methods} and seeds {self.seeds} make it {value}: "
                    "they are derived: delete them (`mapex plan` writes the plan into dvc.yaml)"
                )
        return self


# The class: the user's keys above and one field per derived run list (RUN_LISTS, beside
# derived_lists in pipeline/params/runlists.py), in that order.
RunParams = create_model("RunParams", __base__=_RunParams, __module__=__name__, **RUN_LISTS)
RunParams.__doc__ = _RunParams.__doc__

DERIVED_KEYS = tuple(k for k in RunParams.model_fields if k not in USER_RUN_KEYS)
