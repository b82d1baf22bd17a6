"""Validated params.yaml: one pydantic model per stage section, plus the shared sections.

A stage validates the shared sections and its own section before it touches any artifact.
Every validation failure becomes one `ParamsError` whose message names the file, the key
path, the offending value and what was expected.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError

from pipeline.params.common import DERIVED_KEYS, EnvParams, RunParams
from pipeline.params.planned import context_lists

__all__ = ["ParamsError", "load_params", "section", "EnvParams", "RunParams", "KNOWN_SECTIONS"]

# Top-level keys params.yaml may hold. Shared: env and the lists of RUN_KEYS. The others are the
# stage sections, each named like its stage (dvc.yaml stage = stages/<name>.py = section).
RUN_KEYS = tuple(RunParams.model_fields)  # the top-level lists, validated together by RunParams
# Every stage section and its model (module:class under pipeline/params/), in one table: the
# section names params.yaml may hold and pipeline.params.registry.section_models both come from
# it, so a new section is one line here. Models are imported only by registry (a stage imports
# its own section's model alone: its DVC code deps stay its own).
SECTION_MODELS = {
    "td3": "td3:TD3Params",
    "train_specialist": "train_specialist:TrainSpecialistParams",
    "train_pderl": "train_pderl:TrainPderlParams",
    "import_specialists": "import_specialists:ImportSpecialistsParams",
    "fit_critics": "fit_critics:FitCriticsParams",
    "critic_fidelity": "critic_fidelity:CriticFidelityParams",
    "extract": "extract:ExtractParams",
    "evaluate": "evaluate:EvaluateParams",
    "score": "score:ScoreParams",
    "report": "report:ReportParams",
    "export": "export:ExportParams",
    "render": "render:RenderParams",
    "mopderl": "mopderl:MopderlParams",
    "morld": "morld:MorldParams",
    "interpolate": "interpolate:InterpolateParams",
}
KNOWN_SECTIONS = ("env", *RUN_KEYS, *SECTION_MODELS)

# Keys that moved to another section: an old params file that still has one where it was gets a
# line naming the key and its new home (instead of an "unknown key", or worse, a stage that
# reads the new home and silently takes its default). The TD3 agent's settings moved from
# train_specialist to td3 (pipeline/params/td3.py), which train_pderl and mopderl read too.
MOVED_KEYS: dict[str, tuple[str, tuple[str, ...]]] = {
    "train_specialist": (
        "td3",
        (
            "learning_starts",
            "buffer_size",
            "batch_size",
            "hidden_sizes",
            "actor_lr",
            "critic_lr",
            "gamma",
            "tau",
            "exploration_noise",
            "policy_noise",
            "noise_clip",
            "policy_freq",
            "secondary_critics",
            "cuda_graphs",
        ),
    ),
}

M = TypeVar("M", bound=BaseModel)


class ParamsError(ValueError):
    """params.yaml is missing, unreadable or fails validation; the message says where and why."""


def load_params(path: str | Path, check_plan: bool = True) -> dict[str, Any]:
    """Read params.yaml into a dict, rejecting unknown top-level keys, with the derived run
    lists (pipeline.params.planned.run_lists) merged in. Where a dvc.yaml planned by `mapex plan`
    sits beside it, its recorded plan inputs must still be what the params make them: a stale
    plan is one line naming the key and `mapex plan` (pipeline/params/planned.py). A derived list
    written in the params file itself (a file built by hand for one stage run, outside DVC) is
    kept, and RunParams checks it against what the params make it; beside a planned dvc.yaml it
    is an error (`mapex plan` removes it).
    `check_plan=False` skips the plan's check (`mapex plan`, about to replace it)."""
    path = Path(path)
    raw = _read_mapping(path)
    from pipeline.params.planned import dvc_yaml_beside, run_lists, stale_input

    dvc = dvc_yaml_beside(path)
    if check_plan and path.name == "params.yaml" and dvc.is_file():
        written = [k for k in DERIVED_KEYS if k in raw]
        if written:
            raise ParamsError(
                f"{path}: {written[0]} is derived from methods, variants and seeds: delete it "
                "(`mapex plan` does, and writes what DVC needs of it into dvc.yaml)"
            )
        why = stale_input(raw, dvc.read_text())
        if why:
            raise ParamsError(f"{dvc}: {why}")
    try:
        return run_lists(raw) | raw  # lists written inline are kept: RunParams checks them
    except ValueError:  # bad methods or variants: RunParams' validation names them
        return raw


def _read_mapping(path: Path) -> dict[str, Any]:
    """A params file read and checked to be a mapping of known keys."""
    if not path.is_file():
        raise ParamsError(f"{path}: params file not found")
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ParamsError(f"{path}: not valid YAML ({exc})") from exc
    if not isinstance(raw, dict):
        raise ParamsError(f"{path}: expected a mapping of sections at the top level, got {type(raw).__name__}")
    unknown = sorted(set(raw) - set(KNOWN_SECTIONS))
    if unknown:
        raise ParamsError(f"{path}: unknown top-level key(s) {unknown}; expected some of {list(KNOWN_SECTIONS)}")
    for old, (new, keys) in MOVED_KEYS.items():
        body = raw.get(old)
        moved = [k for k in keys if isinstance(body, dict) and k in body]
        if moved:
            where = ", ".join(f"{old}.{k} -> {new}.{k}" for k in moved)
            raise ParamsError(f"{path}: key(s) moved to section `{new}` (read by every stage that uses them): {where}")
    return raw


def _describe(err: dict[str, Any], prefix: str) -> str:
    loc = ".".join(str(p) for p in (prefix, *err["loc"]) if p != "")
    if not err["loc"]:  # a check across keys (a model validator): its message names the keys
        return f"{prefix or 'top-level lists'}: {err['msg'].removeprefix('Value error, ')}"
    if err["type"] == "extra_forbidden":
        return f"{loc}: unknown key (value {err['input']!r})"
    if err["type"] == "missing":
        return f"{loc}: required key is missing"
    return f"{loc} = {err['input']!r}: {err['msg']}"


def section(raw: dict[str, Any], name: str, model: type[M], path: str | Path = "params.yaml") -> M:
    """Validate section `name` of a loaded params dict with `model`.

    A missing section is validated as empty, so models whose fields all have defaults accept it.
    """
    data = raw.get(name, {})
    context = None
    if model is RunParams:
        data = {k: raw[k] for k in RUN_KEYS if k in raw}
        name = ""
        context = context_lists(raw)
    if data is None:
        data = {}
    try:
        return model.model_validate(data, context=context)
    except ValidationError as exc:
        lines = [_describe(e, name) for e in exc.errors()]
        raise ParamsError(f"{path}: invalid params:\n  " + "\n  ".join(lines)) from None
