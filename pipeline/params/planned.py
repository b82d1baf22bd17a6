"""What a planned dvc.yaml was planned for, and the check that it still is.

A user lists what to run once, in params.yaml (`methods`, `variants`, `seeds`, `objectives`,
import entries, export methods). DVC cannot filter a matrix, so `mapex plan`
(pipeline/params/plan.py) writes dvc.yaml whole from them: only the stages that run, each
matrix written out as a literal list. It records the inputs it planned from at the top of
dvc.yaml, one `# plan input KEY: VALUE` line each (`input_lines`); every stage loads its
params through `pipeline.params.load_params`, which compares them with what params.yaml makes
now and stops in one line naming the key and `mapex plan` when they differ. A module of its
own, apart from the writer, so that every stage's code deps hold only what this check reads.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from pipeline.params.common import DERIVED_KEYS, RunParams
from pipeline.params.runlists import derived_lists

INPUT_PREFIX = "# plan input "
# A dvc.yaml from before the plan loaded its run lists from this file (`vars:`).
OLD_GENERATED = "params.gen.yaml"


def context_lists(raw: dict[str, Any]) -> dict[str, list]:
    """What the derived run lists read besides methods and seeds: import_specialists.policies
    (as "imports") and export.methods (as "export"), [] where absent."""
    imports, export = raw.get("import_specialists") or {}, raw.get("export") or {}
    return {
        "imports": list(imports.get("policies") or []) if isinstance(imports, dict) else [],
        "export": list(export.get("methods") or []) if isinstance(export, dict) else [],
    }


def run_lists(raw: dict[str, Any]) -> dict[str, list]:
    """The derived run lists of a loaded params file (its own keys, RunParams' defaults where
    absent); ValueError (one line) on methods or variants the pipeline cannot run."""
    defaults = RunParams.model_fields
    context = context_lists(raw)
    return derived_lists(
        list(raw.get("methods", defaults["methods"].default)),
        list(raw.get("seeds", defaults["seeds"].default)),
        context["imports"],
        context["export"],
        list(raw.get("objectives", defaults["objectives"].default)),
        raw.get("variants"),
    )


def label_keys(raw: dict[str, Any]) -> list[str]:
    """The params keys of the report's names of the variants `methods` lists (stages render and
    report track them; a variant without a `label` is named by its name, which `methods` holds)."""
    variants = raw.get("variants") if isinstance(raw.get("variants"), dict) else {}
    listed = [str(m) for m in raw.get("methods") or [] if m in variants]
    return sorted(f"variants.{m}.label" for m in listed if isinstance(variants[m], dict) and "label" in variants[m])


def export_keys(raw: dict[str, Any]) -> list[str]:
    """export.methods where params.yaml writes it (stage render tracks it: its explorer links
    the exported files); DVC refuses a tracked key the file lacks, so [] where it does not."""
    export = raw.get("export")
    return ["export.methods"] if isinstance(export, dict) and "methods" in export else []


def plan_inputs(raw: dict[str, Any]) -> dict[str, Any]:
    """What dvc.yaml is planned from: the derived run lists (variant_labels aside: the stages
    track the label keys instead), label_keys and export_keys. ValueError as run_lists."""
    lists = run_lists(raw)
    inputs: dict[str, Any] = {k: lists[k] for k in DERIVED_KEYS if k != "variant_labels"}
    inputs["label_keys"] = label_keys(raw)
    inputs["export_keys"] = export_keys(raw)
    return inputs


def input_lines(inputs: dict[str, Any]) -> str:
    """The `# plan input KEY: VALUE` lines dvc.yaml records `inputs` in (JSON values)."""
    return "".join(f"{INPUT_PREFIX}{k}: {json.dumps(v)}\n" for k, v in inputs.items())


def recorded_inputs(dvc_text: str) -> dict[str, Any] | None:
    """The plan inputs a dvc.yaml's text records; None for a dvc.yaml `mapex plan` did not write."""
    found = {}
    for line in dvc_text.splitlines():
        if line.startswith(INPUT_PREFIX):
            key, _, value = line[len(INPUT_PREFIX) :].partition(": ")
            found[key] = json.loads(value)
        elif line.startswith("stages:"):
            break
    return found or None


def stale_input(raw: dict[str, Any], dvc_text: str) -> str | None:
    """One line saying why a dvc.yaml is stale for params `raw` (the first input whose recorded
    value differs from what `raw` makes it), or None if it is current or was not planned."""
    recorded = recorded_inputs(dvc_text)
    if recorded is None:
        if f"- {OLD_GENERATED}" in dvc_text:
            return f"written before `mapex plan` (it loads {OLD_GENERATED}): run `mapex plan`"
        return None  # a dvc.yaml of the user's own: nothing to check
    try:
        want = plan_inputs(raw)
    except ValueError:
        return None  # bad methods or variants: RunParams' validation names them
    for key, value in want.items():
        if key not in recorded or _differ(recorded[key], value):
            return f"stale: planned for {key} = {recorded.get(key)!r}, but params make it {value!r}: run `mapex plan`"
    return None


def _differ(given: Any, want: Any) -> bool:
    """Whether a recorded list (or mapping) differs from what the params make it, order aside."""
    if isinstance(want, dict) or not isinstance(given, list):
        return given != want
    return sorted(given, key=repr) != sorted(want, key=repr)


def without_derived(params: dict[str, Any]) -> dict[str, Any]:
    """`params` without the derived keys (a loaded params dict carries them; a params file does not)."""
    return {k: v for k, v in params.items() if k not in DERIVED_KEYS}


def with_tracked_env(params: dict[str, Any]) -> dict[str, Any]:
    """`params` with env.reward_terms present (null where it is left out): every stage that builds
    the env lists it, and DVC refuses a listed param missing from the file (`mapex plan` fills
    it in the same way)."""
    env = params.get("env")
    if isinstance(env, dict) and "reward_terms" not in env:
        params = {**params, "env": {**env, "reward_terms": None}}
    return params


def dvc_yaml_beside(params: str | Path) -> Path:
    """The dvc.yaml a params file is planned into: the one in its directory."""
    return Path(params).parent / "dvc.yaml"
