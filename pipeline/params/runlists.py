"""The run lists dvc.yaml fans its producing stages out over (`derived_lists`), computed from
params.yaml's `methods`, `seeds`, `variants` and imports; `mapex plan` writes them into
dvc.yaml's matrices and every stage checks they are current (pipeline/params/planned.py).

Kept apart from the methods table (pipeline/params/methods.py) because it reads both that
table and the named variants (pipeline/params/variants.py), which read the table themselves:
here neither of the two imports the other's reader, so the params package has no import cycle.
"""

from __future__ import annotations

from pipeline.params.methods import (
    JOINT_VARIANTS,
    METHODS,
    SPECIALIST_KINDS,
    TRAINED_KINDS,
    _import_item,
    method_name,
)
from pipeline.params.variants import parse_variants


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
