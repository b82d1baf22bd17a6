"""The params file's side of `mapex plan`: an older generated block and derived lists removed,
and the keys a planned stage tracks filled in at their defaults (DVC refuses a listed param
missing from the file). The plan itself goes to dvc.yaml (pipeline/params/plan.py).
"""

from __future__ import annotations

import json
import re

import yaml

from pipeline.params.common import DERIVED_KEYS, GENERATED_BEGIN, GENERATED_END, EnvParams
from pipeline.params.planned import run_lists


def tidied_text(text: str, where: str = "params.yaml") -> str:
    """`text` (a params file) without a generated block or derived keys (the plan in dvc.yaml
    holds what DVC needs of them now) and with the extract keys stage warmup_only tracks filled in
    (`with_tracked_keys`). Raises ValueError naming `where` if the file is not a mapping, lists an
    unknown method or a set of methods the plan cannot run, or writes a derived key
    over several lines (which this rewrite cannot remove safely)."""
    raw = yaml.safe_load(text)
    if not isinstance(raw, dict):
        raise ValueError(f"{where}: expected a mapping of sections at the top level")
    try:
        run_lists(raw)
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None
    lines = text.splitlines(keepends=True)
    if GENERATED_BEGIN + "\n" in lines:  # an older file: drop the block
        start = lines.index(GENERATED_BEGIN + "\n")
        end = next((i for i in range(start, len(lines)) if lines[i].rstrip("\n") == GENERATED_END), None)
        if end is None:
            raise ValueError(f"{where}: the generated block has no end line ({GENERATED_END!r})")
        lines = lines[:start] + lines[end + 1 :]
    kept = []
    key_line = re.compile(r"^(%s)\s*:(.*)$" % "|".join(DERIVED_KEYS))
    for line in lines:
        m = key_line.match(line)
        if m:
            value = m.group(2).split("#", 1)[0].strip()
            if not value.startswith(("[", "{")):
                raise ValueError(
                    f"{where}: {m.group(1)} is written over several lines; delete it (it is derived from methods)"
                )
            continue
        kept.append(line)
    return with_tracked_keys("".join(kept))


TRACKED_NOTE = (
    "  # named for DVC by `mapex plan` (stages warmup_only, interpolate, train_pderl, mopderl track these "
    "keys); edit freely\n"
)


RENDER_NOTE = "# named for DVC by `mapex plan` (stage render tracks the section): no clips\n"


INTERPOLATE_NOTE = "# named for DVC by `mapex plan` (stage interpolate tracks the section): null = as extract\n"


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
    from pipeline.params.td3 import AGENT_KEYS, TD3Params

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
    try:
        agents = bool(run_lists(raw)["pderl_seeds"])  # stages train_pderl and mopderl list td3's AGENT_KEYS
    except ValueError:
        agents = False  # bad methods: the caller's validation names them
    if agents:
        text = _filled(text, raw, "td3", AGENT_KEYS, TD3Params.model_fields)
    # every stage that builds the env lists env.reward_terms (null for an env with a vector reward)
    text = _filled(text, raw, "env", ("reward_terms",), EnvParams.model_fields)
    return _filled(text, raw, "extract", tracked, ExtractParams.model_fields)


def _filled(text: str, raw: dict, name: str, tracked: tuple[str, ...], fields: dict) -> str:
    """`text` with the keys `tracked` of section `name` that it lacks appended to that section
    (created if absent) at their defaults (`fields`), under TRACKED_NOTE."""
    if not tracked:
        return text
    section = raw.get(name)
    if section is not None and not isinstance(section, dict):
        return text  # not a mapping: the stage's validation names the problem
    missing = [k for k in tracked if k not in (section or {})]
    if not missing:
        return text
    added = [TRACKED_NOTE] + [f"  {k}: {json.dumps(fields[k].default)}\n" for k in missing]
    lines = text.splitlines(keepends=True)
    if lines and not lines[-1].endswith("\n"):
        lines[-1] += "\n"
    start = next((i for i, line in enumerate(lines) if re.match(rf"^{name}\s*:", line)), None)
    if start is None:
        return "".join(lines) + f"\n{name}:\n" + "".join(added)
    if lines[start].split(":", 1)[1].split("#", 1)[0].strip():  # `extract: {...}` in flow style
        return text
    end = start + 1
    while end < len(lines) and (lines[end].startswith((" ", "\t")) or not lines[end].strip()):
        end += 1
    while end > start + 1 and not lines[end - 1].strip():
        end -= 1
    return "".join(lines[:end] + added + lines[end:])
