"""The methods this pipeline can run and compare: one table that params validation, the
derived run lists of the plan (`mapex plan`) and the report all read.

A method is what `methods` in params.yaml lists and what data/fronts/<method>/ holds: an
extraction variant run from one kind of specialists (`mapex_td3` is variant `mapex` from TD3
specialists), or a baseline. Its `variant` is what `mapex extract --variant` takes (None for a
baseline), its `kind` the specialists it starts from (None for MORL/D, which starts from
nothing), its `stage` the template of the stage catalogue (pipeline/params/stage_catalogue.yaml)
that `mapex plan` writes its stage from: one stage per method that runs, named for the method,
and one per named variant of it (pipeline/params/variants.py), a matrix over seeds only.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Literal, NamedTuple

from pydantic import Field


class Method(NamedTuple):
    name: str  # in params.yaml's `methods`, data/fronts/<name>/, every artifact's "method" key
    variant: str | None  # extraction variant (mapex, mapex_posthoc, warmup_only); None for a baseline
    kind: str | None  # the specialists it starts from: td3, pderl; None if none
    stage: str  # the catalogue template its stage (named <name>, writing data/fronts/<name>/) is planned from
    # A built-in variant (the hybrid): the method it varies and what it sets in that method's
    # sections; None for a method of its own. Planned and run as a named variant of `of`
    # (pipeline/params/variants.py), whose definition is here instead of in params.yaml.
    of: str | None = None
    overrides: dict[str, dict] | None = None


# What the hybrid sets in section extract (its identity: a run whose resolved extract.init is
# interpolate is a hybrid, whatever its name).
HYBRID = {"init": "interpolate", "seed_interpolation": 48}

# What each method computes. How the report shows it (label, colour, row order) is presentation,
# kept on the reporting side (pipeline/reporting/presentation.py): this file is in the code
# closure of every stage, so a label here would make a recolouring retrain the specialists.
METHODS: dict[str, Method] = {
    m.name: m
    for m in (
        Method("mapex_pderl", "mapex", "pderl", "extract"),
        Method("mapex_posthoc_pderl", "mapex_posthoc", "pderl", "extract_posthoc"),
        Method("warmup_only_pderl", "warmup_only", "pderl", "warmup_only"),
        Method("mapex_td3", "mapex", "td3", "extract"),
        Method("mapex_posthoc_td3", "mapex_posthoc", "td3", "extract_posthoc"),
        Method("warmup_only_td3", "warmup_only", "td3", "warmup_only"),
        # the hybrid extraction (not in the paper; docs/manual.md, "Hybrid extraction"): MAPEX-TD3
        # whose children start from their parents' mixed weights, its population seeded with the
        # interpolation grid (48 seeds: the studies' form, as many as interpolate_td3 makes at 64
        # units). A params.yaml entry variants.hybrid_td3 {of: mapex_td3, ...} may refine it.
        Method("hybrid_td3", "mapex", "td3", "extract", "mapex_td3", {"extract": HYBRID}),
        Method("mapex_posthoc_imported", "mapex_posthoc", "imported", "extract_posthoc"),
        Method("warmup_only_imported", "warmup_only", "imported", "warmup_only"),
        # the weight-space interpolation baseline (not in the paper): pipeline/baselines/interpolate.py
        Method("interpolate_pderl", None, "pderl", "interpolate"),
        Method("interpolate_td3", None, "td3", "interpolate"),
        Method("interpolate_imported", None, "imported", "interpolate"),
        Method("mopderl", None, "pderl", "mopderl"),
        Method("morld", None, None, "morld"),
    )
}

# Extraction variants (`mapex extract --variant`): what each changes in section `extract`. Each
# method has a stage of its own, so MAPEX with joint critics does not depend on post-hoc critics
# (its stage lists no data/posthoc dep) and warm-up only tracks only the extract keys it reads
# (pipeline.params.extract.WARMUP_ONLY_KEYS): DVC deps and params cannot depend on a matrix value.
EXTRACT_VARIANTS = ("mapex", "mapex_posthoc", "warmup_only")
# Kinds of specialists extraction can start from: td3 (stage train_specialist), pderl (stage
# train_pderl) and imported (stage import_specialist: trained elsewhere, no joint critics, so
# only MAPEX-PostHoc and warm-up only, which reads no critics, extract from them; an objective
# without an import entry gets a slot trained here by TD3, stage train_specialist_imported, and
# its critics are fitted post hoc too, so every objective is judged by critics of one kind),
# under data/specialists/<kind>/seedS.
SPECIALIST_KINDS = ("td3", "pderl", "imported")
# The kinds trained here with critics of their own (stage extract's joint variants read them).
TRAINED_KINDS = ("td3", "pderl")
BASELINES = tuple(m.name for m in METHODS.values() if m.variant is None)
# The built-in variants (rows with `of`): the hybrid.
BUILTIN_VARIANTS = tuple(m.name for m in METHODS.values() if m.of is not None)
# The report's rows for the starting policies alone (no method made them): names a variant may
# not take (their labels: pipeline/reporting/presentation.py).
SPECIALISTS_ROWS = tuple(f"specialists_{k}" for k in SPECIALIST_KINDS)


def method_name(variant: str, kind: str) -> str:
    """The method an extraction variant from one kind of specialists is: mapex_td3, mapex_posthoc_pderl, ..."""
    return f"{variant}_{kind}"


def statistics_beside(model: str) -> str | None:
    """The SB3 VecNormalize statistics saved beside model file `model` in rl-zoo3's layout, if
    one is there (relative paths are taken from the working directory, the repository root):

    - `<prefix>_vecnormalize_<N>_steps.pkl` beside a checkpoint `<prefix>_<N>_steps.zip` (SB3's
      CheckpointCallback with save_vecnormalize, which rl-zoo3 uses: the statistics of that step);
    - `<stem>/vecnormalize.pkl` beside `<stem>.zip` (rl-zoo3's run folder `<algo>/<env>_<n>/`
      holds the final model `<env>.zip` and its statistics in `<env>/vecnormalize.pkl`);
    - `<env>/vecnormalize.pkl` beside any other model of a run folder `<env>_<n>` (its
      best_model.zip, whose statistics rl-zoo3 saves there too).

    The first that exists, as a path of the same form as `model`; None if none does. A file
    under any other name (the Hugging Face Hub's vec_normalize.pkl) must be named in `normalize`:
    a folder may hold several models and one statistics file, and a wrong guess would be silent.
    """
    p = Path(model)
    candidates = []
    step = re.fullmatch(r"(.+)_(\d+)_steps", p.stem)
    if step:
        candidates.append(p.with_name(f"{step.group(1)}_vecnormalize_{step.group(2)}_steps.pkl"))
    candidates.append(p.parent / p.stem / "vecnormalize.pkl")
    run = re.fullmatch(r"(.+)_\d+", p.parent.name)
    if run:
        candidates.append(p.parent / run.group(1) / "vecnormalize.pkl")
    return next((c.as_posix() for c in candidates if c.is_file()), None)


def normalize_file(entry: dict) -> str | None:
    """The observation statistics file of import entry `entry` (import_specialists.policies[],
    as a dict): its `normalize` path; None where it says false; where it says nothing, the file
    rl-zoo3 saves beside an sb3 model (`statistics_beside`), else None."""
    given = entry.get("normalize")
    if isinstance(given, str):
        return given
    if given is False or entry.get("format") != "sb3":
        return None
    return statistics_beside(str(entry["file"]))


def _import_item(entry: dict, *keys: str) -> dict:
    """One entry of import_collect / import_buffered: `keys` of the entry, and its statistics as
    stage import_specialist takes them: normalize, the file or "none", and normalize_dep, what
    DVC tracks for it (the file, or the policy file again where there is none: a DVC dep cannot
    be optional, and a matrix item cannot add one)."""
    stats = normalize_file(entry)
    return {k: entry[k] for k in keys} | {"normalize": stats or "none", "normalize_dep": stats or entry["file"]}


# The run lists derived_lists returns, each as (type, pydantic Field): RunParams
# (pipeline/params/common.py) has one field per entry, so a new run list is its line here and its
# value in derived_lists, in this one file. Lists of ints are checked unique and >= 0, lists of
# named choices (Literal) unique.
RUN_LISTS: dict[str, tuple[Any, Any]] = {
    "td3_seeds": (
        list[int] | None,
        Field(
            None,
            description="derived: seeds of stage train_specialist (TD3 specialists); dvc.yaml needs it written, "
            "validation accepts it left out",
        ),
    ),
    "pderl_seeds": (list[int], Field([], description="derived: seeds of stage train_pderl (PDERL specialists)")),
    "imported_seeds": (
        list[int],
        Field([], description="derived: seeds of stage import_specialist (imported specialists)"),
    ),
    "import_collect": (
        list[dict],
        Field([], description="derived: import_specialists.policies whose buffer stage import_specialist collects"),
    ),
    "import_buffered": (
        list[dict],
        Field(
            [],
            description="derived: import_specialists.policies that bring a buffer (stage import_specialist_buffered)",
        ),
    ),
    "import_train": (
        list[int],
        Field(
            [],
            description="derived: objectives without an import_specialists.policies entry, whose slots of the imported "
            "kind stage train_specialist_imported trains here by TD3",
        ),
    ),
    "fidelity_from": (
        list[Literal["td3", "pderl"]],
        Field(
            ["td3"],
            description="derived: kinds of trained specialists whose joint critics stage critic_fidelity scores",
        ),
    ),
    "posthoc_from": (
        list[Literal["td3", "pderl", "imported"]],
        Field(
            [], description="derived: kinds to fit post-hoc critics for (stage fit_critics) and run MAPEX-PostHoc from"
        ),
    ),
    "export_methods": (list[str], Field([], description="derived: export.methods, the fronts stage export writes")),
    "specialist_variants": (
        list[str],
        Field(
            [],
            description="derived: the specialists variants the method variants start from (train_specialist_variant)",
        ),
    ),
    "method_runs": (
        list[dict],
        Field(
            [],
            description="derived: one stage per method that runs (name, template stage, variant, kind, specialists, of)",
        ),
    ),
    "run_seeds": (list[int], Field([], description="derived: seeds, as dvc.yaml's matrices read them")),
    "run_objectives": (list[int], Field([], description="derived: objectives, as dvc.yaml's matrices read them")),
    "run_methods": (list[str], Field([], description="derived: methods, as dvc.yaml's matrices read them")),
    "variant_labels": (
        dict[str, str],
        Field({}, description="derived: the report's names of the variants run (stages report and render track them)"),
    ),
}
