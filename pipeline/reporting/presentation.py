"""How the report and the explorer show each method: its name on the page, its colour in the
figures, and the order of the rows. Presentation only, on the reporting side.

This module is imported by the stages that draw (report, render, grid-report) and by nothing that
trains, extracts or evaluates, so a new label or colour reruns only those stages: `dvc repro`
never retrains a specialist for a change to a plot (tests/test_dvc_pipeline.py checks it). What a
method computes (its extraction variant, the specialists it starts from, its stage) is
pipeline/params/methods.py's METHODS; every name there has a row here (tests/test_methods_table.py).
"""

from __future__ import annotations

from typing import NamedTuple

from pipeline.params.methods import METHODS, SPECIALIST_KINDS, Method


class Look(NamedTuple):
    label: str  # its name in the report (the paper's where it has one)
    colour: str  # its colour in the report's figures (matplotlib)


# In the report's usual order: the paper's MAPEX first.
LOOKS: dict[str, Look] = {
    "mapex_pderl": Look("MAPEX", "tab:blue"),
    "mapex_posthoc_pderl": Look("MAPEX-PostHoc", "tab:cyan"),
    "warmup_only_pderl": Look("warm-up only (PDERL)", "tab:gray"),
    "mapex_td3": Look("MAPEX-TD3", "tab:green"),
    "mapex_posthoc_td3": Look("MAPEX-TD3-PostHoc", "tab:olive"),
    "warmup_only_td3": Look("warm-up only (TD3)", "tab:orange"),
    "hybrid_td3": Look("hybrid (interpolated start)", "darkgreen"),
    "mapex_posthoc_imported": Look("MAPEX-PostHoc (imported)", "tab:brown"),
    "warmup_only_imported": Look("warm-up only (imported)", "tab:pink"),
    "interpolate_pderl": Look("interpolation (PDERL)", "darkcyan"),
    "interpolate_td3": Look("interpolation (TD3)", "goldenrod"),
    "interpolate_imported": Look("interpolation (imported)", "rosybrown"),
    "mopderl": Look("MOPDERL", "tab:red"),
    "morld": Look("MORL/D", "tab:purple"),
}
METHOD_ORDER = tuple(LOOKS)  # the report's rows, built-in methods first (variants after them)

# The report's rows for the starting policies alone (no method made them).
SPECIALISTS_LABELS = {
    "specialists_pderl": "PDERL specialists only",
    "specialists_td3": "TD3 specialists only",
    "specialists_imported": "imported specialists only",
}
assert set(SPECIALISTS_LABELS) == {f"specialists_{k}" for k in SPECIALIST_KINDS}

# The named variants of the params file the report is for (pipeline/params/variants.py), as
# Method rows (kind: the specialists they start from, a kind or a specialists variant's name,
# whose report rows are its own) with their looks. Set once per process by `use_variants` (stages
# report and render); empty otherwise, when a variant's name is its label.
VARIANT_METHODS: dict[str, Method] = {}
VARIANT_LOOKS: dict[str, Look] = {}
VARIANT_BASES: dict[str, str] = {}  # method variant -> the method it varies
SPECIALIST_VARIANT_LABELS: dict[str, str] = {}
# The methods of the report that run the hybrid extraction (resolved extract.init: interpolate;
# pipeline.params.variants.is_hybrid): their verdicts against warm-up only name the start.
HYBRID_METHODS: set[str] = set()
# The variants' colours in the figures, in the order they are declared (none of LOOKS').
VARIANT_COLOURS = ("tab:pink", "black", "darkorange", "mediumseagreen", "slateblue", "crimson", "teal", "olive")


def use_variants(variants: dict, hybrids: set[str] | frozenset[str] = frozenset()) -> None:
    """Make the report name, colour and order the method variants of `variants` (name -> a
    pipeline.params.variants.Variant) and their specialists (specialists_<name> rows); `hybrids`:
    the methods that run the hybrid extraction. A built-in variant (the hybrid) keeps its row of
    LOOKS (its colour; its label unless the params entry gives one)."""
    VARIANT_METHODS.clear()
    VARIANT_LOOKS.clear()
    VARIANT_BASES.clear()
    SPECIALIST_VARIANT_LABELS.clear()
    HYBRID_METHODS.clear()
    HYBRID_METHODS.update(hybrids)
    method_variants = [v for v in variants.values() if not v.is_specialists]
    own = [v for v in method_variants if v.name not in LOOKS]  # the colours go to the file's own
    for v in method_variants:
        VARIANT_METHODS[v.name] = Method(v.name, METHODS[v.of].variant, v.specialists, v.stage)
        if v.name in LOOKS:
            builtin = LOOKS[v.name]
            VARIANT_LOOKS[v.name] = Look(builtin.label if v.label == v.name else v.label, builtin.colour)
        else:
            VARIANT_LOOKS[v.name] = Look(v.label, VARIANT_COLOURS[own.index(v) % len(VARIANT_COLOURS)])
        VARIANT_BASES[v.name] = v.of
    for v in variants.values():
        if v.is_specialists:
            SPECIALIST_VARIANT_LABELS[f"specialists_{v.name}"] = f"{v.label} specialists only"


def label(method: str) -> str:
    """The method's name in the report (its own name if it is not in the table)."""
    look = VARIANT_LOOKS.get(method) or LOOKS.get(method)
    if look:
        return look.label
    return SPECIALISTS_LABELS.get(method) or SPECIALIST_VARIANT_LABELS.get(method, method)


def colour(method: str) -> str:
    look = VARIANT_LOOKS.get(method) or LOOKS.get(method)
    return look.colour if look else "grey"


def specialist_kind(method: str) -> str | None:
    """The specialists a method starts from ('pderl', 'td3', or a specialists variant's name),
    None if none or unknown."""
    m = METHODS.get(method) or VARIANT_METHODS.get(method)
    return m.kind if m else None
