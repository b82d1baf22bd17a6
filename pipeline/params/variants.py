"""Named variants: a method or a kind of specialists run again under a name of its own, with
some keys of the sections its stage reads set to other values.

params.yaml declares them in one mapping, `variants`, and lists the method variants that run in
`methods` beside the plain methods:

    methods: [mapex_td3, mapex_td3_gentle, interpolate_td3, interpolate_td3_shared]
    variants:
      mapex_td3_gentle: {of: mapex_td3, extract: {epochs: 2, beta: 5.0}}
      td3_shared: {of: td3, td3: {shared_init: true}}
      interpolate_td3_shared: {of: interpolate_td3, specialists: td3_shared}

A variant's keys: `of` (required: the method, or for specialists the kind, it varies), `label`
(its name in the report; default: its own name), for a method variant `specialists` (a
specialists variant of the method's kind to start from; default: the kind's own), and one
mapping per section it overrides, merged key by key over that section of the file, so any key
of the section can be varied (a new key of a section becomes a variant override with no work
here). Only the sections the base's stage reads may be overridden (VARIANT_SECTIONS), so an
override always changes what runs.

A mapping, not entries of the `methods` list, because DVC tracks params by key path: the
variant's stage (one stage per method that runs, named for it, planned by `mapex plan`; a
specialists variant's: train_specialist_variant) lists `variants.<name>`, so changing one
variant's override reruns that variant's stages and nothing else, and `dvc exp run -S variants.<name>.extract.epochs=3` needs no regeneration.

Where a variant's values come from: the stage reads the base sections of the file with the
variant's overrides merged in (`with_overrides`), and validates the result with the section's
own model (a bad override is named with its `variants.<name>` path). DVC tracks the base section
and `variants.<name>`: together they fix the resolved values. A change to a base key that a
variant overrides still reruns the variant (harmless: it computes the same numbers, and the
stage's outputs then leave everything after it up to date).

Built-in variants: a METHODS row with `of` (the hybrid, `hybrid_td3`) is a variant whose
definition is in code, so `methods: [hybrid_td3]` runs it with no `variants` entry (its stage
then tracks no `variants.hybrid_td3`: the definition is a code dep). An entry of that name
refines it (its overrides merged over the built-in's; `of` must stay the built-in's base and the
hybrid's extract.init interpolate), and a variant `of: hybrid_td3` is a variant of its base with
the hybrid's keys set: the studies' presets, written before the hybrid had a name, keep their
entries and so their stages unchanged.
"""

from __future__ import annotations

import copy
import re
from typing import Any, NamedTuple

from pipeline.params.methods import BUILTIN_VARIANTS, METHODS, SPECIALIST_KINDS, SPECIALISTS_ROWS

# What a variant of each base may override (the sections that base's stage reads). Every method of
# METHODS may be varied: the plan gives each variant a stage of its own, planned from its base's
# template (pipeline/params/stage_catalogue.yaml), so a variant of any base is an edit of params.yaml.
VARIANT_SECTIONS: dict[str, tuple[str, ...]] = {
    "extract": ("extract",),
    "warmup_only": ("extract",),
    "extract_posthoc": ("extract",),
    "interpolate": ("interpolate", "extract"),
    "mopderl": ("mopderl",),
    "morld": ("morld",),
}
# Specialists variants, by kind: the sections their training stage reads, and that stage.
SPECIALIST_VARIANT_SECTIONS: dict[str, tuple[str, ...]] = {"td3": ("td3", "train_specialist")}
SPECIALIST_VARIANT_STAGES = {"td3": "train_specialist_variant"}
# Bases whose variants may start from a specialists variant (`specialists`): those that read the
# specialists alone. MAPEX-PostHoc reads critics fitted for its kind's own specialists (stage
# fit_critics) and MOPDERL the PDERL specialists, so their variants start from the kind's own.
FROM_SPECIALIST_VARIANTS = ("extract", "warmup_only", "interpolate")
NAME = re.compile(r"^[a-z][a-z0-9_]*$")


class Variant(NamedTuple):
    name: str
    of: str  # the base: a METHODS name, or a kind of specialists for a specialists variant
    kind: str | None  # the kind of specialists (td3, pderl, imported); None for MORL/D's, which starts from none
    specialists: str | None  # what it starts from (data/specialists/<specialists>/): a kind or a specialists variant
    label: str  # its name in the report
    overrides: dict[str, dict]  # section -> keys set to other values
    stage: str  # the template its stage is planned from (its base's, METHODS' stage); train_specialist_variant

    @property
    def is_specialists(self) -> bool:
        return self.of in SPECIALIST_KINDS


def parse_variants(raw: Any, where: str = "variants") -> dict[str, Variant]:
    """The variants of params' `variants` mapping (None or absent: none), specialists variants
    first resolved so that method variants can point at them. ValueError, one line naming the
    key path, value and what was expected, on a bad entry."""
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise ValueError(f"{where} = {raw!r}: expected a mapping of name -> {{of: <method or kind>, ...}}")
    out: dict[str, Variant] = {}
    order = sorted(raw, key=lambda n: not (isinstance(raw[n], dict) and raw[n].get("of") in SPECIALIST_KINDS))
    for name in order:
        body, here = raw[name], f"{where}.{name}"
        if not isinstance(name, str) or not NAME.match(name):
            raise ValueError(f"{where}: name {name!r}: expected lower-case letters, digits and _ (a folder name)")
        builtin = METHODS.get(name) if name in BUILTIN_VARIANTS else None
        if (name in METHODS and builtin is None) or name in SPECIALIST_KINDS or name in SPECIALISTS_ROWS:
            raise ValueError(f"{here}: the name is taken by a built-in method or kind; choose another")
        if not isinstance(body, dict) or "of" not in body:
            raise ValueError(f"{here} = {body!r}: expected a mapping with `of` (the method or kind it varies)")
        of = body["of"]
        if builtin is not None and of != builtin.of:
            raise ValueError(
                f"{here}.of = {of!r}: {name} is the built-in hybrid, a variant of {builtin.of!r}; an entry of "
                f"that name refines it (of: {builtin.of}); name a variant of {of} of your own instead"
            )
        if of in SPECIALIST_KINDS:
            sections = SPECIALIST_VARIANT_SECTIONS.get(of)
            if sections is None:
                raise ValueError(
                    f"{here}.of = {of!r}: specialists variants are of kind {list(SPECIALIST_VARIANT_SECTIONS)} only"
                )
            kind, specialists, stage = of, name, SPECIALIST_VARIANT_STAGES[of]
            allowed = ("of", "label", *sections)
        elif of in METHODS:
            base = METHODS[of]
            sections = VARIANT_SECTIONS[base.stage]
            kind, stage = base.kind, base.stage
            specialists = body.get("specialists", kind)
            if specialists != kind:
                spec = out.get(specialists)
                if base.stage not in FROM_SPECIALIST_VARIANTS:
                    raise ValueError(
                        f"{here}.specialists = {specialists!r}: a variant of {of} starts from its own kind's "
                        f"specialists ({kind!r}); variants of {[m.name for m in METHODS.values() if m.stage in FROM_SPECIALIST_VARIANTS]} "
                        "may start from a specialists variant"
                    )
                if spec is None or not spec.is_specialists or spec.kind != kind:
                    raise ValueError(
                        f"{here}.specialists = {specialists!r}: expected {kind!r} or the name of a specialists variant "
                        f"of kind {kind} in {where} ({{of: {kind}, ...}})"
                    )
            allowed = ("of", "label", "specialists", *sections)
        else:
            raise ValueError(
                f"{here}.of = {of!r}: expected a method of {list(METHODS)} or a kind of specialists "
                f"{list(SPECIALIST_VARIANT_SECTIONS)}"
            )
        stray = [k for k in body if k not in allowed]
        if stray:
            raise ValueError(
                f"{here}: key {stray[0]!r} is not one of {list(allowed)} (a variant of {of} may override "
                f"sections {list(sections)}, those its stage reads)"
            )
        overrides = {s: body[s] for s in sections if s in body}
        for s, value in overrides.items():
            if not isinstance(value, dict):
                raise ValueError(f"{here}.{s} = {value!r}: expected a mapping of that section's keys")
        if builtin is not None:
            overrides = _refined(builtin, overrides, here)
        elif of in BUILTIN_VARIANTS:  # a variant of the hybrid: a variant of its base, the hybrid's keys set
            overrides, of = _refined(METHODS[of], overrides, here), METHODS[of].of
        label = body.get("label", name)
        if not isinstance(label, str) or not label:
            raise ValueError(f"{here}.label = {label!r}: expected a non-empty string")
        out[name] = Variant(name, of, kind, specialists, label, overrides, stage)
    # in the file's order, then the built-in variants the file does not refine
    return {n: out[n] for n in raw} | {n: builtin_variant(n) for n in BUILTIN_VARIANTS if n not in raw}


def builtin_variant(name: str) -> Variant:
    """Built-in variant `name` of METHODS (the hybrid) as its definition in code gives it."""
    m = METHODS[name]
    assert m.of is not None and m.overrides is not None, name
    base = METHODS[m.of]
    return Variant(name, m.of, base.kind, base.kind, name, copy.deepcopy(m.overrides), base.stage)


def _refined(builtin: Any, overrides: dict[str, dict], where: str) -> dict[str, dict]:
    """A params entry's `overrides` of built-in variant `builtin` merged over the built-in's own;
    the keys that make it what it is (the hybrid's extract.init) may not be set otherwise."""
    out = copy.deepcopy(builtin.overrides)
    for section, over in overrides.items():
        out[section] = {**out.get(section, {}), **copy.deepcopy(over)}
    for section, fixed in builtin.overrides.items():
        if "init" in fixed and out[section].get("init") != fixed["init"]:
            raise ValueError(
                f"{where}.{section}.init = {out[section].get('init')!r}: {builtin.name} is the built-in hybrid, "
                f"whose children start from interpolated weights ({section}.init: {fixed['init']}); name a variant "
                f"of {builtin.of} of your own for another start"
            )
    return out


def is_hybrid(raw: dict[str, Any], method: str, variants: dict[str, Variant]) -> bool:
    """Does `method` (a METHODS name or a variant of `variants`, parse_variants of the loaded
    params `raw`) run the hybrid extraction: an extraction (MAPEX or MAPEX-PostHoc) whose
    resolved extract.init, the file's section with the variant's overrides, is interpolate?"""
    v = variants.get(method)
    base = METHODS.get(v.of if v is not None else method)
    if base is None or base.stage not in ("extract", "extract_posthoc"):
        return False
    resolved = with_overrides(raw, v) if v is not None else raw
    return (resolved.get("extract") or {}).get("init") == "interpolate"


def with_overrides(raw: dict[str, Any], variant: Variant) -> dict[str, Any]:
    """A copy of the loaded params `raw` with `variant`'s overrides merged into their sections,
    key by key (a nested mapping is merged too; a list or value replaces the file's)."""

    def merge(base: Any, over: dict) -> dict:
        out = copy.deepcopy(base) if isinstance(base, dict) else {}
        for k, v in over.items():
            out[k] = merge(out.get(k), v) if isinstance(v, dict) else copy.deepcopy(v)
        return out

    out = dict(raw)
    for section, over in variant.overrides.items():
        out[section] = merge(raw.get(section), over)
    return out
