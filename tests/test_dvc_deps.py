"""dvc.yaml's code deps cannot drift: each stage lists exactly the project files its module runs.

A stage's code deps must equal the transitive in-project import closure of its module
(stages/<stage>.py, or the one codedeps.STAGE_MODULES names; computed by pipeline.core.codedeps,
the same function extract's resume fingerprint uses) plus stages/cli.py (the `mapex` entry point, which sets the torch thread
count and so the results' last bits). An import added without its dep (an edit that would
change results without a rerun) or a stale dep (a rerun for nothing) fails here;
`python -m pipeline.core.codedeps` rewrites them.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from pipeline.core.codedeps import ROOT, module_closure, stage_module

STAGES = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]


def code_deps(stage: dict) -> set[str]:
    return {d for d in stage.get("deps", []) if d.startswith(("pipeline/", "stages/"))}


@pytest.mark.parametrize("name", sorted(STAGES))
def test_stage_code_deps_are_its_import_closure(name):
    expected = set(module_closure(stage_module(name))) | {"stages/cli.py"}
    got = code_deps(STAGES[name])
    assert not expected - got, f"dvc.yaml stage {name} misses deps {sorted(expected - got)} (fix: python -m pipeline.core.codedeps)"
    assert not got - expected, f"dvc.yaml stage {name} lists deps it does not import {sorted(got - expected)} (fix: python -m pipeline.core.codedeps)"


def test_every_stage_has_its_module():
    """Each stage's module exists and is the one its command runs (`mapex <sub>` = stages/<sub>.py),
    so the closure above is that of the code that actually runs."""
    for name, stage in STAGES.items():
        module = stage_module(name)
        assert (ROOT / (module.replace(".", "/") + ".py")).is_file(), name
        sub = stage["cmd"].split()[1].replace("-", "_")
        assert f"stages.{sub}" == module, f"stage {name} runs `mapex {stage['cmd'].split()[1]}` but its deps follow {module}"


def test_closure_follows_from_imports_and_package_inits(tmp_path, monkeypatch):
    """codedeps on a toy project: `from a import b` pulls module a.b and a's __init__, relative
    imports resolve against the package, and imports of other projects are ignored."""
    import pipeline.core.codedeps as cd

    pkg = tmp_path / "pipeline"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("from . import leaf\n")
    (pkg / "sub" / "leaf.py").write_text("import numpy\n")
    (pkg / "top.py").write_text("from pipeline.sub import thing\nimport os\n")
    (pkg / "unused.py").write_text("")
    monkeypatch.setattr(cd, "ROOT", Path(tmp_path))
    cd.module_closure.cache_clear()
    try:
        assert cd.module_closure("pipeline.top") == (
            "pipeline/__init__.py", "pipeline/sub/__init__.py", "pipeline/sub/leaf.py", "pipeline/top.py",
        )
    finally:
        cd.module_closure.cache_clear()
