"""Every method of the table (pipeline/params/methods.py: METHODS) is wired into each of the six
places docs/developing.md ("Adding a method") lists: (1) its algorithm's module, imported by its
stage; (2) params models for the sections its stage reads, each in SECTION_MODELS; (3) its row,
with a label and colour of its own, and a stage of its own planned from its template (derived_lists'
method_runs); (4) a stage module that `mapex` finds as a subcommand; (5) a dvc.yaml
stage writing its front; (6) its sections in params.yaml, a test and docs/manual.md naming it.
A new row that misses one fails here, naming the method and the place; a test below checks that
the doc lists six places."""

from __future__ import annotations

import re

import pytest
import yaml

from pipeline.core.codedeps import ROOT
from pipeline.params import KNOWN_SECTIONS, SECTION_MODELS, RunParams
from pipeline.params.methods import METHODS, RUN_LISTS
from pipeline.params.plan import CATALOGUE, catalogue_modules, code_deps
from pipeline.params.registry import section_models
from pipeline.params.runlists import derived_lists
from pipeline.reporting.presentation import LOOKS
from stages.cli import COMMANDS

STAGES = yaml.safe_load(CATALOGUE.read_text())["stages"]  # every stage, matrices over named lists
PARAMS = yaml.safe_load((ROOT / "params.yaml").read_text())
MANUAL = (ROOT / "docs" / "manual.md").read_text()
TESTS = "".join(p.read_text() for p in sorted((ROOT / "tests").glob("test_*.py")))
IMPORTS = [{"objective": k, "file": f"models/obj{k}.zip", "format": "sb3"} for k in (0, 1)]


@pytest.mark.parametrize("name", list(METHODS))
def test_a_method_is_wired_into_every_place(name):
    m = METHODS[name]
    # the dvc.yaml stage that writes its front, running a registered stage module
    assert m.stage in STAGES, f"{name}: no dvc.yaml stage {m.stage!r}"
    stage = STAGES[m.stage]
    assert "data/fronts/" in " ".join(map(str, stage["outs"])), f"{name}: stage {m.stage} writes no front"
    module = catalogue_modules()[m.stage]
    command = re.match(r"mapex ([\w-]+)", stage["cmd"]).group(1)
    assert COMMANDS.get(command) == module, f"{name}: stage {m.stage} runs `mapex {command}`, not {module}"
    assert (ROOT / (module.replace(".", "/") + ".py")).is_file(), f"{name}: no {module}"
    # listed alone, the plan gives it a stage of its own from that template, over the seeds
    lists = derived_lists([name], [0], IMPORTS if m.kind == "imported" else None)
    runs = [r for r in lists["method_runs"] if r["name"] == name]
    assert [r["stage"] for r in runs] == [m.stage], f"{name}: the plan writes it no stage from template {m.stage}"
    matrix = [v[2:-1] for v in stage["matrix"].values()]
    assert matrix == ["run_seeds"], f"{name}: template {m.stage}'s matrix is over {matrix}, not the seeds only"
    # the params sections its stage reads are known to params.yaml and have a model
    sections = {p.split(".")[0] for p in stage.get("params", []) if isinstance(p, str)}
    for s in sections:
        assert s in KNOWN_SECTIONS, f"{name}: section {s!r} (stage {m.stage}) is not in KNOWN_SECTIONS"
        assert s in section_models() or s in ("seeds", "objectives", "methods"), f"{name}: no model for {s!r}"
    # and a name and colour of its own in the report
    # its look in the report, on the reporting side (pipeline/reporting/presentation.py), unique
    assert name in LOOKS, f"{name}: no label and colour in pipeline/reporting/presentation.py LOOKS"
    look = LOOKS[name]
    assert [x.label for x in LOOKS.values()].count(look.label) == 1, f"{name}: label {look.label!r} is not unique"
    assert [x.colour for x in LOOKS.values()].count(look.colour) == 1, f"{name}: colour {look.colour!r} is not unique"
    # place 2: each section's model is one line of SECTION_MODELS, a module of pipeline/params/
    for s in sections - {"env", "seeds", "objectives", "methods", "variants"}:
        assert s in SECTION_MODELS, f"{name}: section {s!r} (stage {m.stage}) has no line in SECTION_MODELS"
        module = SECTION_MODELS[s].split(":")[0]
        assert (ROOT / "pipeline" / "params" / f"{module}.py").is_file(), f"{name}: no pipeline/params/{module}.py"
    # place 3: the run lists its stage fans out over are in RUN_LISTS, so fields of RunParams
    for key in matrix:
        assert key in RUN_LISTS, f"{name}: run list {key!r} (stage {m.stage}) has no entry in RUN_LISTS"
        assert key in RunParams.model_fields, f"{name}: run list {key!r} (stage {m.stage}) is not a RunParams field"
    # place 1: the stage imports an algorithm module of pipeline/ beyond params and core
    closure = stage_closure(m.stage)
    algorithm = [f for f in closure if f.startswith("pipeline/") and f.split("/")[1] not in ("params", "core")]
    assert algorithm, f"{name}: stage {m.stage} imports no algorithm module of pipeline/"
    # place 6: params.yaml holds the sections its stage reads; a test and the manual name it
    missing = sorted(s for s in sections if s not in PARAMS)
    assert not missing, f"{name}: params.yaml has no {missing} (stage {m.stage} reads them)"
    assert f'"{name}"' in TESTS, f"{name}: no test names it"
    assert re.search(rf"(?<![\w-]){name}(?![\w-])", MANUAL), f"{name}: docs/manual.md does not name it"


def stage_closure(stage: str) -> list[str]:
    """The code deps the plan writes for a stage (its import closure, as paths)."""
    return list(code_deps(catalogue_modules()[stage]))


def test_developing_md_lists_six_places_to_add_a_method():
    """The doc's list is what the test above checks: six numbered places, at most."""
    doc = (ROOT / "docs" / "developing.md").read_text()
    section = doc[doc.index("## Adding a method") : doc.index("## Adding a variant")]
    steps = re.findall(r"^(\d+)\. ", section, flags=re.M)
    assert steps == [str(i) for i in range(1, len(steps) + 1)] and len(steps) <= 6, steps


def test_every_run_list_of_derived_lists_is_declared_once():
    """derived_lists computes exactly the lists RUN_LISTS declares (RunParams' derived fields)."""
    assert list(derived_lists(["mapex_td3", "warmup_only_td3"], [0])) == list(RUN_LISTS)


def test_every_method_has_a_look_and_every_look_a_method():
    """Labels and colours sit on the reporting side, one row per method of METHODS, none stray."""
    assert set(LOOKS) == set(METHODS)
