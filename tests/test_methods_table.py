"""Every method of the table (pipeline/params/methods.py: METHODS) is wired into each place
docs/developing.md ("Adding a method") lists: a dvc.yaml stage whose command is a registered
stage module, a run list of derived_lists that gives that stage an item, params sections that
are known and modelled, and a label and colour of its own. A new row that misses one fails here,
naming the method and the place."""

from __future__ import annotations

import re

import pytest
import yaml

from pipeline.core.codedeps import ROOT, stage_module
from pipeline.params import KNOWN_SECTIONS
from pipeline.params.methods import JOINT_VARIANTS, METHODS, TRAINED_KINDS, derived_lists, method_name
from pipeline.params.registry import section_models
from stages.cli import COMMANDS

STAGES = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
IMPORTS = [{"objective": k, "file": f"models/obj{k}.zip", "format": "sb3"} for k in (0, 1)]
# lists every method's matrix reads whatever it is (not the method's own)
SHARED_LISTS = {"run_seeds", "run_objectives", "run_methods"}


def runnable(name: str) -> list[str]:
    """`name` with the methods dvc.yaml's matrices need beside it (extract and warmup_only run the
    whole product of joint variants x trained kinds)."""
    m = METHODS[name]
    if m.stage in ("extract", "warmup_only") and m.kind in TRAINED_KINDS:
        return [method_name(v, m.kind) for v in JOINT_VARIANTS]
    return [name]


@pytest.mark.parametrize("name", list(METHODS))
def test_a_method_is_wired_into_every_place(name):
    m = METHODS[name]
    # the dvc.yaml stage that writes its front, running a registered stage module
    assert m.stage in STAGES, f"{name}: no dvc.yaml stage {m.stage!r}"
    stage = STAGES[m.stage]
    assert "data/fronts/" in " ".join(map(str, stage["outs"])), f"{name}: stage {m.stage} writes no front"
    module = stage_module(m.stage)
    command = re.match(r"mapex ([\w-]+)", stage["cmd"]).group(1)
    assert COMMANDS.get(command) == module, f"{name}: stage {m.stage} runs `mapex {command}`, not {module}"
    assert (ROOT / (module.replace(".", "/") + ".py")).is_file(), f"{name}: no {module}"
    # a run list of derived_lists gives that stage an item when the method is listed
    lists = derived_lists(runnable(name), [0], IMPORTS if m.kind == "imported" else None)
    matrix = [v[2:-1] for v in stage["matrix"].values()]
    missing = [key for key in matrix if key not in SHARED_LISTS and not lists.get(key)]
    assert not missing, f"{name}: derived_lists leaves {missing} (stage {m.stage}'s matrix) empty"
    # the params sections its stage reads are known to params.yaml and have a model
    sections = {p.split(".")[0] for p in stage.get("params", []) if isinstance(p, str)}
    for s in sections:
        assert s in KNOWN_SECTIONS, f"{name}: section {s!r} (stage {m.stage}) is not in KNOWN_SECTIONS"
        assert s in section_models() or s in ("seeds", "objectives", "methods"), f"{name}: no model for {s!r}"
    # and a name and colour of its own in the report
    assert [x.label for x in METHODS.values()].count(m.label) == 1, f"{name}: label {m.label!r} is not unique"
    assert [x.colour for x in METHODS.values()].count(m.colour) == 1, f"{name}: colour {m.colour!r} is not unique"
