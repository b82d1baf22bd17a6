"""The run lists dvc.yaml fans its producing stages out over (`derived_lists`), computed from
params.yaml's `methods`, `seeds`, `variants` and imports; `mapex plan` writes them into
dvc.yaml's matrices and every stage checks they are current (pipeline/params/planned.py).

Kept apart from the methods table (pipeline/params/methods.py) because it reads both that
table and the named variants (pipeline/params/variants.py), which read the table themselves:
here neither of the two imports the other's reader, so the params package has no import cycle.
"""

from __future__ import annotations

from typing import Any

from pipeline.params.methods import METHODS, SPECIALIST_KINDS, TRAINED_KINDS, Method, _import_item
from pipeline.params.variants import Variant, parse_variants


def derived_lists(
    methods: list[str],
    seeds: list[int],
    imports: list[dict] | None = None,
    export: list[str] | None = None,
    objectives: list[int] | tuple[int, ...] = (0, 1),
    variants: dict | None = None,
) -> dict[str, list]:
    """The lists dvc.yaml is planned from, derived from `methods`, `seeds`, `imports`
    (import_specialists.policies, as dicts), `export` (section export's methods, each of which
    must be in `methods`), `objectives` and `variants` (params' mapping of named variants,
    pipeline/params/variants.py, which `methods` may list beside the plain methods):

    - method_runs: one entry per method that runs (`method_run`): the plan writes each its own
      stage, named for it, from its base's template, with a matrix over run_seeds;
    - td3_seeds, pderl_seeds, imported_seeds: the seeds of the specialists some method starts
      from (train_specialist, train_pderl, import_specialist); specialist_variants: the
      specialists variants method variants start from (train_specialist_variant);
    - import_collect / import_buffered: the import entries whose buffer is collected and those
      that bring one (their stages differ in a DVC dep); each item also names its observation
      statistics (`_import_item`), found on disk in rl-zoo3's layout where the entry names none
      (`normalize_file`); import_train: the objectives of `objectives` (RunParams' default
      [0, 1]) without an entry, whose slots of the imported kind train_specialist_imported
      trains here by TD3 (an entry for an objective outside `objectives` raises ValueError);
    - fidelity_from: the trained kinds whose joint critics critic_fidelity scores (those
      joint-critic extraction starts from; with none, the trained kinds the methods start
      from, td3 when none does, unless only imported specialists are used); posthoc_from: the
      kinds MAPEX-PostHoc (or a variant of it) starts from, whose critics fit_critics fits;
    - export_methods, run_seeds, run_objectives, run_methods, variant_labels.

    Unknown methods raise ValueError naming them, and so does an imported method without
    import_specialists.policies or a listed specialists variant."""

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
    listed = list(methods)
    # every method that runs, plain or a variant, as the base it is planned from
    bases = [METHODS[parsed[m].of] if m in parsed else METHODS[m] for m in listed]
    from_kind = {v.kind for v in named if v.specialists == v.kind}  # variants from a kind's own specialists
    joint = [b for b in bases if b.stage in ("extract", "warmup_only") and b.kind in TRAINED_KINDS]
    # the trained kinds whose joint critics stage critic_fidelity scores: those joint-critic
    # extraction starts from; with none, the trained kinds the methods start from (td3 when none
    # does, unless only imported specialists are used)
    kinds = [k for k in TRAINED_KINDS if any(b.kind == k for b in joint)]
    uses_imported = any(b.kind == "imported" for b in bases)
    if not kinds:
        kinds = [k for k in TRAINED_KINDS if any(b.kind == k for b in bases)] or ([] if uses_imported else ["td3"])
    posthoc = [k for k in SPECIALIST_KINDS if any(b.stage == "extract_posthoc" and b.kind == k for b in bases)]
    # the kinds trained here that some method starts from as they are (a variant from a specialists
    # variant starts from that variant's, stage train_specialist_variant)
    own = {METHODS[m].kind for m in listed if m in METHODS} | from_kind
    entries = [dict(e) for e in imports or []]
    if uses_imported and not entries:
        raise ValueError(
            f"methods = {listed} start from imported specialists, but import_specialists.policies is empty: "
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
        "td3_seeds": list(seeds) if "td3" in kinds or "td3" in own else [],
        "pderl_seeds": list(seeds) if "pderl" in own else [],
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
        "fidelity_from": kinds,
        "posthoc_from": posthoc,
        "export_methods": list(export or []),
        "specialist_variants": list(dict.fromkeys(v.specialists for v in named if v.specialists != v.kind)),
        # one stage per method that runs, planned from its base's template (pipeline/params/plan.py)
        "method_runs": [method_run(m, b, parsed.get(m), m in (variants or {})) for m, b in zip(listed, bases)],
        # every matrix of dvc.yaml reads this file only (a stale file still gives a consistent graph)
        "run_seeds": list(seeds),
        "run_objectives": list(objectives),
        "run_methods": listed,
        # the report's and the explorer's names of the variants run (their stages track this)
        "variant_labels": {v.name: v.label for v in named}
        | {v.specialists: parsed[v.specialists].label for v in named if v.specialists != v.kind},
    }


def method_run(name: str, base: Method, variant: Variant | None, in_file: bool = True) -> dict[str, Any]:
    """One method's stage as the plan writes it: its name (the stage's and data/fronts/<name>/),
    the template it is planned from (its base's stage in METHODS), the extraction variant its
    command takes, its kind, the specialists it starts from (data/specialists/<specialists>/),
    and for a named variant the base it varies (`of`: its command then takes --method and its
    stage tracks variants.<name>). `base` is the METHODS row it is planned from (the variant's
    `of`, or the method itself). A built-in variant (the hybrid) that params' `variants` does
    not refine (`in_file` false) is marked `builtin`: its stage tracks no variants.<name>, which
    the file lacks (its definition is code, a dep of the stage)."""
    run = {
        "name": name,
        "stage": base.stage,
        "variant": base.variant,
        "kind": base.kind,
        "specialists": variant.specialists if variant is not None else base.kind,
        "of": variant.of if variant is not None else None,
    }
    return run | {"builtin": True} if variant is not None and not in_file else run
