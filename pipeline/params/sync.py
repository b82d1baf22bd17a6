"""Write the derived run lists into a params file: the text behind `mapex sync-params`.

A user lists what to run once (`methods`, with `seeds`); the lists dvc.yaml fans its
producing stages out over follow from them (pipeline.params.methods.derived_lists) and live
in a generated block of params.yaml, between GENERATED_BEGIN and GENERATED_END, right after
`methods`. Syncing replaces that block (or, in an older file, the hand-written one-line
entries of those keys) and leaves every other line, comments included, as it was.
"""

from __future__ import annotations

import json
import re

import yaml

from pipeline.params.common import GENERATED_BEGIN, GENERATED_END, RunParams
from pipeline.params.methods import derived_lists

# the generated lists: RunParams' fields other than those written by hand, in its order
DERIVED_KEYS = tuple(k for k in RunParams.model_fields if k not in ("seeds", "objectives", "methods", "variants"))


def generated_block(
    methods: list[str],
    seeds: list[int],
    imports: list[dict] | None = None,
    export: list[str] | None = None,
    objectives: list[int] | tuple[int, ...] = (0, 1),
    variants: dict | None = None,
) -> str:
    lists = derived_lists(methods, seeds, imports, export, objectives, variants)
    lines = [f"{key}: {json.dumps(lists[key])}" for key in DERIVED_KEYS]
    return "\n".join([GENERATED_BEGIN, *lines, GENERATED_END]) + "\n"


def synced_text(text: str, where: str = "params.yaml") -> str:
    """`text` (a params file) with its generated block rewritten from its `methods` and `seeds`,
    and the extract keys stage warmup_only tracks filled in (`with_tracked_keys`).

    Raises ValueError naming `where` if the file is not a mapping, lists an unknown method or a
    set of methods that dvc.yaml's matrices cannot run, or writes a derived key over several
    lines outside the generated block (which this rewrite cannot remove safely)."""
    raw = yaml.safe_load(text)
    if not isinstance(raw, dict):
        raise ValueError(f"{where}: expected a mapping of sections at the top level")
    defaults = RunParams.model_fields
    methods = raw.get("methods", defaults["methods"].default)
    seeds = raw.get("seeds", defaults["seeds"].default)
    objectives = raw.get("objectives", defaults["objectives"].default)
    from pipeline.params import context_lists

    context = context_lists(raw)
    try:
        block = generated_block(
            list(methods), list(seeds), context["imports"], context["export"], list(objectives), raw.get("variants")
        )
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None
    lines = text.splitlines(keepends=True)
    if GENERATED_BEGIN + "\n" in lines:  # replace the block in place
        start = lines.index(GENERATED_BEGIN + "\n")
        end = next((i for i in range(start, len(lines)) if lines[i].rstrip("\n") == GENERATED_END), None)
        if end is None:
            raise ValueError(f"{where}: the generated block has no end line ({GENERATED_END!r})")
        return with_tracked_keys("".join(lines[:start]) + block + "".join(lines[end + 1 :]))
    kept = []
    key_line = re.compile(r"^(%s)\s*:(.*)$" % "|".join(DERIVED_KEYS))
    for line in lines:
        m = key_line.match(line)
        if m:
            value = m.group(2).split("#", 1)[0].strip()
            if not value.startswith("["):
                raise ValueError(
                    f"{where}: {m.group(1)} is written over several lines; delete it (it is derived from methods)"
                )
            continue
        kept.append(line)
    at = next((i for i, line in enumerate(kept) if re.match(r"^methods\s*:", line)), None)
    if at is None:  # no methods line: the block goes after seeds, or at the top
        at = next((i for i, line in enumerate(kept) if re.match(r"^seeds\s*:", line)), -1)
    while at >= 0 and at + 1 < len(kept) and kept[at + 1].startswith((" ", "\t", "-")):
        at += 1  # a methods list over several lines
    return with_tracked_keys("".join(kept[: at + 1]) + block + "".join(kept[at + 1 :]))


TRACKED_NOTE = (
    "  # named for DVC by `mapex sync-params` (stages warmup_only, interpolate track these keys); edit freely\n"
)


RENDER_NOTE = "# named for DVC by `mapex sync-params` (stage render tracks the section): no clips\n"


INTERPOLATE_NOTE = "# named for DVC by `mapex sync-params` (stage interpolate tracks the section): null = as extract\n"


def with_tracked_keys(text: str) -> str:
    """`text` with every extract key a listed stage tracks present, at its default where
    missing, a `render` section (`methods: []`, under RENDER_NOTE) where it has none and, where
    an interpolation method is listed, an `interpolate` section (under INTERPOLATE_NOTE).

    Stage warmup_only lists the extract keys of WARMUP_ONLY_KEYS one by one in dvc.yaml (so
    that changing an advantage-weighted key, which it does not read, leaves it up to date), stage
    interpolate those of INTERPOLATE_EXTRACT_KEYS, and DVC refuses to run a stage whose listed
    params are missing from the file. Missing keys are appended to the extract section (created
    if absent) under TRACKED_NOTE; nothing else changes, and a file without warm-up-only or
    interpolation methods is returned as it is (but for the render section)."""
    from pipeline.params.extract import WARMUP_ONLY_KEYS, ExtractParams
    from pipeline.params.interpolate import INTERPOLATE_EXTRACT_KEYS

    raw = yaml.safe_load(text) or {}
    if "render" not in raw:  # stage render tracks the whole section: DVC needs it in the file
        text = text + ("" if text.endswith("\n") or not text else "\n") + RENDER_NOTE + "render:\n  methods: []\n"
    variants = raw.get("variants") if isinstance(raw.get("variants"), dict) else {}
    # a variant's name stands for its base method (its stage tracks the same keys)
    methods = [str((variants.get(m) or {}).get("of", m)) if m in variants else str(m) for m in raw.get("methods") or []]
    interpolates = any(m.startswith("interpolate_") for m in methods)
    if interpolates and "interpolate" not in raw:  # stage interpolate tracks the whole section
        text = (
            text
            + ("" if text.endswith("\n") or not text else "\n")
            + INTERPOLATE_NOTE
            + "interpolate:\n  policies: null\n  eval_episodes: null\n"
        )
    tracked = WARMUP_ONLY_KEYS if any(m.startswith("warmup_only_") for m in methods) else ()
    tracked += tuple(k for k in INTERPOLATE_EXTRACT_KEYS if interpolates and k not in tracked)
    if not tracked:
        return text
    section = raw.get("extract")
    if section is not None and not isinstance(section, dict):
        return text  # not a mapping: the stage's validation names the problem
    missing = [k for k in tracked if k not in (section or {})]
    if not missing:
        return text
    fields = ExtractParams.model_fields
    added = [TRACKED_NOTE] + [f"  {k}: {json.dumps(fields[k].default)}\n" for k in missing]
    lines = text.splitlines(keepends=True)
    if lines and not lines[-1].endswith("\n"):
        lines[-1] += "\n"
    start = next((i for i, line in enumerate(lines) if re.match(r"^extract\s*:", line)), None)
    if start is None:
        return "".join(lines) + "\nextract:\n" + "".join(added)
    if lines[start].split(":", 1)[1].split("#", 1)[0].strip():  # `extract: {...}` in flow style
        return text
    end = start + 1
    while end < len(lines) and (lines[end].startswith((" ", "\t")) or not lines[end].strip()):
        end += 1
    while end > start + 1 and not lines[end - 1].strip():
        end -= 1
    return "".join(lines[:end] + added + lines[end:])
