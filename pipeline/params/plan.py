"""The planner: dvc.yaml written whole from params.yaml (`mapex plan`).

The pipeline's stages live in one catalogue beside this module (stage_catalogue.yaml: each
stage's matrix, cmd, params, outs and data deps, its matrices over named run lists). From a
params file's methods, variants, seeds, objectives, import entries and export methods
(pipeline.params.planned.plan_inputs) the plan writes one stage per method that runs, named for
it, from its base's template (`method_block`), keeps the other stages that run (a stage whose
matrix has an empty list runs nothing and is left out), writes each list into its matrix as a literal,
expands the catalogue's `${labels}` and `${export_and_labels}` params lines to the keys stages
render and report track, and appends each stage's code deps: the import closure of the module
its `mapex` command runs (pipeline.core.codedeps) plus stages/cli.py. The inputs go at the top of
dvc.yaml, where every stage checks them (pipeline/params/planned.py).

Line-based, so the catalogue's comments reach dvc.yaml as written.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

from pipeline.core.codedeps import ROOT, module_closure
from pipeline.params.methods import METHODS
from pipeline.params.planned import dvc_yaml_beside, input_lines, plan_inputs

CATALOGUE = Path(__file__).with_name("stage_catalogue.yaml")
# The catalogue's method templates: each METHODS row's stage, written once per method that runs.
TEMPLATES = frozenset(m.stage for m in METHODS.values())
# The line above each stage's code deps in dvc.yaml: the plan writes them, not a person.
CODE_MARKER = "      # planned: the code this stage imports (`mapex plan`); do not edit\n"
HEADER = (
    "# The MAPEX pipeline (docs/manual.md), planned by `mapex plan` from {source} and the stage catalogue\n"
    "# (pipeline/params/stage_catalogue.yaml): only the stages that run, their matrices written out. Do not\n"
    "# edit: after changing methods, variants, seeds, objectives, import entries or export methods run\n"
    "# `mapex plan`; every stage checks the inputs below against {source} and names it when they are stale.\n"
    "# Each stage shows its matrix, cmd, params and outs first, then its deps: data deps, then its code.\n"
)
_STAGE = re.compile(r"^  ([a-z0-9_]+):\s*$")
_MATRIX_LIST = re.compile(r"^      ([a-z0-9_]+): \$\{([a-z0-9_]+)\}\s*$")
_COMMAND = re.compile(r"\bmapex ([a-z][a-z-]*)")


def stage_blocks(text: str) -> tuple[list[str], list[tuple[str, list[str]]], list[str]]:
    """A catalogue's (or planned dvc.yaml's) lines split into (what precedes `stages:`, the
    stages as (name, lines), what follows the stages: plots and the rest)."""
    lines = text.splitlines(keepends=True)
    first = lines.index("stages:\n")
    last = next((i for i in range(first + 1, len(lines)) if lines[i].strip() and not lines[i][0].isspace()), len(lines))
    starts = [i for i in range(first + 1, last) if _STAGE.match(lines[i])]
    blocks = [
        (_STAGE.match(lines[s]).group(1), lines[s : (starts[n + 1] if n + 1 < len(starts) else last)])
        for n, s in enumerate(starts)
    ]
    return lines[: first + 1], blocks, lines[last:]


def stage_module(block: list[str]) -> str:
    """The module a stage runs, from the first `mapex <command>` of its cmd: 'stages.extract'."""
    for line in block:
        m = _COMMAND.search(line)
        if m:
            return "stages." + m.group(1).replace("-", "_")
    raise ValueError(f"stage {block[0].strip()} runs no `mapex` command")


def catalogue_modules(catalogue: Path = CATALOGUE) -> dict[str, str]:
    """Every catalogue stage and the module it runs (stage name -> 'stages.<module>')."""
    _, blocks, _ = stage_blocks(catalogue.read_text())
    return {name: stage_module(block) for name, block in blocks}


def code_deps(module: str, root: Path = ROOT) -> list[str]:
    """A stage's code deps: `module`'s import closure under `root` and stages/cli.py, sorted."""
    return sorted(set(module_closure(module, root)) | {"stages/cli.py"})


def plan_text(raw: dict[str, Any], source: str = "params.yaml", root: Path = ROOT) -> str:
    """The dvc.yaml planned for loaded params `raw` (from file `source`) from the catalogue of the
    checkout at `root` (this one by default), with code deps found there. ValueError (one line)
    on methods or variants that cannot run."""
    inputs = plan_inputs(raw)
    _, blocks, tail = stage_blocks((root / CATALOGUE.relative_to(ROOT)).read_text())
    out = [HEADER.format(source=source), input_lines(inputs), "stages:\n"]
    for name, block in blocks:
        if name in TEMPLATES:
            for run in (r for r in inputs["method_runs"] if r["stage"] == name):
                out += _planned_block(method_block(block, run), inputs, root) or []
            continue
        planned = _planned_block(block, inputs, root)
        if planned is not None:
            out += planned
    return "".join(out + tail)


def method_block(template: list[str], run: dict[str, Any]) -> list[str]:
    """A method template's lines written for one method that runs (an entry of the method_runs
    list, pipeline.params.runlists.method_run): the stage named for the method, its placeholders
    filled in, and for a named variant its --method option and its `variants.<name>` params key
    (none for a built-in variant the file does not refine: its definition is code)."""
    name, variant = run["name"], run["of"] is not None
    fill = {
        "{method}": name,
        "{kind}": str(run["kind"]),
        "{specialists}": str(run["specialists"]),
        "{variant}": str(run["variant"]),
        "{method_option}": f" --method {name}" if variant else "",
    }
    out = [f"  {name}:\n"]
    for line in template[1:]:
        if line.strip() == "- {variant_params}":
            if variant and not run.get("builtin"):
                out.append(line.replace("{variant_params}", f"variants.{name}"))
            continue
        for key, value in fill.items():
            line = line.replace(key, value)
        out.append(line)
    return out


def _planned_block(block: list[str], inputs: dict[str, Any], root: Path) -> list[str] | None:
    """One stage's lines as planned, or None where a matrix list of it is empty."""
    tail: list[str] = []
    block = list(block)
    while block and not block[-1].strip():  # blank lines between stages stay between them
        tail.insert(0, block.pop())
    out = []
    for line in block:
        m = _MATRIX_LIST.match(line)
        if m:
            value = inputs[m.group(2)]
            if not value:
                return None
            out.append(f"      {m.group(1)}: {json.dumps(value)}\n")
        elif line.strip() in ("- ${labels}", "- ${export_and_labels}"):
            keys = inputs["label_keys"]
            if "export" in line:
                keys = inputs["export_keys"] + keys
            out += [f"      - {k}\n" for k in keys]
        else:
            out.append(line)
    if not any(line.rstrip() == "    deps:" for line in out):
        out.append("    deps:\n")
    code = [CODE_MARKER] + [f"      - {c}\n" for c in code_deps(stage_module(block), root)]
    return out + code + tail


def write_plan(raw: dict[str, Any], params: Path, root: Path = ROOT) -> Path:
    """Write the plan for params file `params` (loaded as `raw`) to the dvc.yaml beside it,
    atomically. Returns that path."""
    from pipeline.core.artifacts import write_text_atomic

    path = dvc_yaml_beside(params)
    write_text_atomic(path, plan_text(raw, Path(params).name, root))
    return path
