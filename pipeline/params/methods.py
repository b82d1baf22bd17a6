"""The methods this pipeline can run and compare: one table that params validation, the
derived run lists of params.gen.yaml (`mapex sync-params`) and the report all read.

A method is what `methods` in params.yaml lists and what data/fronts/<method>/ holds: an
extraction variant run from one kind of specialists (`mapex_td3` is variant `mapex` from TD3
specialists), or a baseline. Its `variant` is what `mapex extract --variant` takes (None for a
baseline), its `kind` the specialists it starts from (None for MORL/D, which starts from
nothing), its `stage` the dvc.yaml stage that writes its front.
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
    stage: str  # the dvc.yaml stage writing data/fronts/<name>/


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

# Extraction variants (stage extract --variant): what each changes in section `extract`.
EXTRACT_VARIANTS = ("mapex", "mapex_posthoc", "warmup_only")
# The variants run from the specialists' own directories (stages extract and warmup_only), in
# one product with the kinds of extract_from (the trained kinds; warmup_only_imported, which
# reads no critics, is outside the product: stage warmup_only runs it when it is listed). mapex_posthoc reads critics fitted post hoc and
# has its own stage (extract_posthoc), so that extraction with joint critics does not depend on
# post-hoc critics: DVC deps cannot depend on a matrix value. warmup_only has its own stage too,
# whose params are only the extract keys it reads (pipeline.params.extract.WARMUP_ONLY_KEYS):
# DVC params cannot depend on a matrix value either.
JOINT_VARIANTS = ("mapex", "warmup_only")
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
    "extract_from": (
        list[Literal["td3", "pderl"]],
        Field(["td3"], description="derived: kinds of specialists stage extract starts from (td3, pderl)"),
    ),
    "extract_variants": (
        list[Literal["mapex"]],
        Field(
            ["mapex"],
            description="derived: variants stage extract runs from each kind, with the joint critics",
        ),
    ),
    "warmup_from": (
        list[Literal["td3", "pderl", "imported"]] | None,
        Field(
            None,
            description="derived: kinds of specialists stage warmup_only (the warm-up-only ablation) starts from; "
            "dvc.yaml needs it written, validation accepts it left out",
        ),
    ),
    "posthoc_from": (
        list[Literal["td3", "pderl", "imported"]],
        Field(
            [], description="derived: kinds to fit post-hoc critics for (stage fit_critics) and run MAPEX-PostHoc from"
        ),
    ),
    "interpolate_from": (
        list[Literal["td3", "pderl", "imported"]],
        Field([], description="derived: kinds of specialists the interpolation baseline mixes (stage interpolate)"),
    ),
    "mopderl_seeds": (list[int], Field([], description="derived: seeds of the MOPDERL baseline (stage mopderl)")),
    "morld_seeds": (list[int], Field([], description="derived: seeds of the MORL/D baseline (stage morld)")),
    "export_methods": (list[str], Field([], description="derived: export.methods, the fronts stage export writes")),
    "specialist_variants": (
        list[str],
        Field(
            [],
            description="derived: the specialists variants the method variants start from (train_specialist_variant)",
        ),
    ),
    "extract_variant_runs": (
        list[dict],
        Field([], description="derived: method variants of MAPEX and warm-up only (stage extract_variant)"),
    ),
    "interpolate_variant_runs": (
        list[dict],
        Field([], description="derived: method variants of the interpolation baseline (stage interpolate_variant)"),
    ),
    "run_seeds": (list[int], Field([], description="derived: seeds, as dvc.yaml's matrices read them")),
    "run_objectives": (list[int], Field([], description="derived: objectives, as dvc.yaml's matrices read them")),
    "run_methods": (list[str], Field([], description="derived: methods, as dvc.yaml's matrices read them")),
    "variant_labels": (
        dict[str, str],
        Field({}, description="derived: the report's names of the variants run (stages report and render track them)"),
    ),
}


def derived_lists(
    methods: list[str],
    seeds: list[int],
    imports: list[dict] | None = None,
    export: list[str] | None = None,
    objectives: list[int] | tuple[int, ...] = (0, 1),
    variants: dict | None = None,
) -> dict[str, list]:
    """The run lists dvc.yaml fans its producing stages out over, derived from `methods`,
    `seeds` and `imports` (import_specialists.policies, as dicts): td3_seeds, pderl_seeds,
    imported_seeds, import_collect, import_buffered, import_train, extract_from, extract_variants (stage
    extract's), warmup_from (stage warmup_only's kinds), posthoc_from, mopderl_seeds,
    morld_seeds, and export_methods from `export` (section export's methods, each of which must
    be in `methods`). DVC cannot filter a matrix, so each
    producing stage needs a list of its own.

    extract and warmup_only run every joint variant from every trained kind of `extract_from`
    (a matrix), so their methods from td3 and pderl specialists must form that whole product;
    raises ValueError naming the missing method otherwise. warmup_only_imported is outside the
    product: it adds "imported" to warmup_from alone. Unknown methods raise ValueError too, and
    so does an imported method without import_specialists.policies. extract_from also drives
    critic_fidelity (the joint critics' scores): with no joint-critic method it names the
    trained kinds the methods start from (td3 when none does, unless only imported
    specialists are used). import_collect / import_buffered split the import entries into those
    whose buffer is collected and those that bring one (their stages differ in a DVC dep); each
    item also names its observation statistics (`_import_item`), found on disk in rl-zoo3's
    layout where the entry names none (`normalize_file`).

    The entries may cover only some of `objectives` (the top-level list; RunParams' default
    [0, 1]): import_train lists the others, whose slots of the imported kind stage
    train_specialist_imported trains here by TD3. An entry for an objective outside
    `objectives` raises ValueError naming it.

    `variants` (params' mapping of named variants, pipeline/params/variants.py) names the
    method variants `methods` may list: each runs in its base stage's variant twin
    (extract_variant_runs, interpolate_variant_runs: {name, kind, specialists, ...}) from the
    specialists it names, whose specialists variants train in train_specialist_variant
    (specialist_variants); a variant from a kind's own specialists needs that kind trained."""
    from pipeline.params.variants import parse_variants

    parsed = parse_variants(variants)
    listed_specialists = [m for m in methods if m in parsed and parsed[m].is_specialists]
    if listed_specialists:
        name = listed_specialists[0]
        raise ValueError(
            f"methods lists {name!r}, a specialists variant: point a method variant at it "
            f"(variants: {{my_method: {{of: <method>, specialists: {name}}}}}) and list that"
        )
    named = [parsed[m] for m in methods if m in parsed]
    unknown = [m for m in methods if m not in METHODS and m not in parsed]
    if unknown:
        raise ValueError(f"unknown methods {unknown}: expected entries of {list(METHODS)} or names in variants")
    listed, methods = list(methods), [m for m in methods if m not in parsed]  # the plain methods, from here on
    chosen = [METHODS[m] for m in methods]
    from_kind = {v.kind for v in named if v.specialists == v.kind}  # variants from a kind's own specialists
    extract = [m for m in chosen if m.stage in ("extract", "warmup_only") and m.kind in TRAINED_KINDS]
    kinds = [k for k in TRAINED_KINDS if any(m.kind == k for m in extract)]
    variants = [v for v in JOINT_VARIANTS if any(m.variant == v for m in extract)]
    missing = [method_name(v, k) for k in kinds for v in variants if method_name(v, k) not in methods]
    if missing:
        raise ValueError(
            f"methods = {methods}: stage extract runs every variant of {variants} from every kind of {kinds} "
            f"(a DVC matrix), so add {missing} (or drop the methods that need them)"
        )
    uses_imported = any(m.kind == "imported" for m in chosen)
    if not kinds:  # no joint-critic extraction: extract runs no item, and critic_fidelity (a matrix over
        # extract_from) scores the joint critics of the trained specialists the methods start from
        kinds = [k for k in TRAINED_KINDS if any(m.kind == k for m in chosen) or k in from_kind] or (
            [] if uses_imported else ["td3"]
        )
    posthoc = [k for k in SPECIALIST_KINDS if method_name("mapex_posthoc", k) in methods]
    needs_pderl = any(m.kind == "pderl" for m in chosen) or "pderl" in from_kind
    entries = [dict(e) for e in imports or []]
    if uses_imported and not entries:
        raise ValueError(
            f"methods = {methods} start from imported specialists, but import_specialists.policies is empty: "
            "name the policy file of at least one objective (docs/import_export.md)"
        )
    stray_objectives = [e["objective"] for e in entries if e.get("objective") not in objectives]
    if uses_imported and stray_objectives:
        raise ValueError(
            f"import_specialists.policies: objective {stray_objectives[0]} is not one of objectives = {list(objectives)}"
        )
    # the objectives without an import entry: trained here by TD3 (stage train_specialist_imported)
    imported_objectives = {e["objective"] for e in entries}
    import_train = [k for k in objectives if k not in imported_objectives] if uses_imported else []
    imported_seeds = list(seeds) if uses_imported else []
    stray = [m for m in export or [] if m not in listed]
    if stray:
        raise ValueError(f"export.methods lists {stray}, which methods = {listed} does not run")
    return {
        "td3_seeds": list(seeds)
        if "td3" in kinds or any(m.kind == "td3" for m in chosen) or "td3" in from_kind
        else [],
        "pderl_seeds": list(seeds) if needs_pderl else [],
        "imported_seeds": imported_seeds,
        "import_collect": [_import_item(e, "objective", "file", "format") for e in entries if not e.get("buffer")]
        if uses_imported
        else [],
        "import_buffered": [
            _import_item(e, "objective", "file", "format", "buffer") for e in entries if e.get("buffer")
        ]
        if uses_imported
        else [],
        "import_train": import_train,
        "extract_from": kinds,
        "extract_variants": [v for v in variants if v != "warmup_only"],
        "warmup_from": (kinds if "warmup_only" in variants else [])
        + (["imported"] if method_name("warmup_only", "imported") in methods else []),
        "posthoc_from": posthoc,
        "interpolate_from": [k for k in SPECIALIST_KINDS if method_name("interpolate", k) in methods],
        "mopderl_seeds": list(seeds) if "mopderl" in methods else [],
        "morld_seeds": list(seeds) if "morld" in methods else [],
        "export_methods": list(export or []),
        "specialist_variants": list(dict.fromkeys(v.specialists for v in named if v.specialists != v.kind)),
        "extract_variant_runs": [
            {"name": v.name, "variant": METHODS[v.of].variant, "kind": v.kind, "specialists": v.specialists}
            for v in named
            if v.stage == "extract_variant"
        ],
        "interpolate_variant_runs": [
            {"name": v.name, "kind": v.kind, "specialists": v.specialists}
            for v in named
            if v.stage == "interpolate_variant"
        ],
        # every matrix of dvc.yaml reads this file only (a stale file still gives a consistent graph)
        "run_seeds": list(seeds),
        "run_objectives": list(objectives),
        "run_methods": listed,
        # the report's and the explorer's names of the variants run (their stages track this)
        "variant_labels": {v.name: v.label for v in named}
        | {v.specialists: parsed[v.specialists].label for v in named if v.specialists != v.kind},
    }
