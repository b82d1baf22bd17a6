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
    assert not expected - got, (
        f"dvc.yaml stage {name} misses deps {sorted(expected - got)} (fix: python -m pipeline.core.codedeps)"
    )
    assert not got - expected, (
        f"dvc.yaml stage {name} lists deps it does not import {sorted(got - expected)} (fix: python -m pipeline.core.codedeps)"
    )


def test_every_stage_has_its_module():
    """Each stage's module exists and is the one its command runs (`mapex <sub>` = stages/<sub>.py),
    so the closure above is that of the code that actually runs."""
    for name, stage in STAGES.items():
        module = stage_module(name)
        assert (ROOT / (module.replace(".", "/") + ".py")).is_file(), name
        sub = stage["cmd"].split()[1].replace("-", "_")
        assert f"stages.{sub}" == module, (
            f"stage {name} runs `mapex {stage['cmd'].split()[1]}` but its deps follow {module}"
        )


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
            "pipeline/__init__.py",
            "pipeline/sub/__init__.py",
            "pipeline/sub/leaf.py",
            "pipeline/top.py",
        )
    finally:
        cd.module_closure.cache_clear()


# The shell's one rule: a stage module imports the library and the shared stage helpers, never
# another stage (the `mapex` entry point, which registers every stage, is the exception).
SHARED_STAGE_MODULES = {"stages.common"}


def stage_imports(path: Path) -> set[str]:
    import ast

    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
            found |= {f"{node.module}.{a.name}" for a in node.names}
        elif isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
    return {
        name for name in found if name.startswith("stages.") and (ROOT / (name.replace(".", "/") + ".py")).is_file()
    }


@pytest.mark.parametrize("path", sorted((ROOT / "stages").glob("*.py")), ids=lambda p: p.name)
def test_no_stage_imports_another_stage(path):
    if path.name in ("cli.py", "__init__.py", "common.py"):
        return
    others = stage_imports(path) - SHARED_STAGE_MODULES
    assert not others, (
        f"stages/{path.name} imports {sorted(others)}: move what it needs into pipeline/ (stages import pipeline only)"
    )


def test_stage_import_check_sees_an_import_of_another_stage(tmp_path):
    """The check above is not blind: a stage that imports another is caught, in both spellings."""
    bad = tmp_path / "bad.py"
    bad.write_text("from stages.extract import extract\nimport stages.report\nfrom stages.common import progress\n")
    assert stage_imports(bad) - SHARED_STAGE_MODULES == {"stages.extract", "stages.report"}


@pytest.mark.parametrize("name", ["train_specialist", "train_pderl", "mopderl", "fit_critics", "morld"])
def test_an_edit_to_extraction_code_reruns_no_training_stage(name):
    """MAPEX's own code (pipeline/extraction/) is no dep of the specialists, the post-hoc
    critics or the baselines: editing it must not rerun them (nor void their checkpoints).
    tests/test_dvc_pipeline.py checks the same with `dvc status` after a real edit."""
    deps = sorted(d for d in code_deps(STAGES[name]) if d.startswith("pipeline/extraction/"))
    assert not deps, f"stage {name} depends on {deps}"
