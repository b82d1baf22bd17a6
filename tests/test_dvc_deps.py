"""The plan's stages (every one of the catalogue, planned for tests/support EVERY_STAGE) and the
committed dvc.yaml: each stage lists exactly the project files its module runs.

A stage's code deps must equal the transitive in-project import closure of the module its
`mapex` command runs (computed by pipeline.core.codedeps, the same function extract's resume
fingerprint uses) plus stages/cli.py (the `mapex` entry point, which sets the torch thread count
and so the results' last bits). The plan writes them; the committed dvc.yaml must be what
`mapex plan` writes for params.yaml today, so an import added without its dep (an edit that would
change results without a rerun) or a stale dep (a rerun for nothing) fails here.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml
from support.tiny_params import EVERY_STAGE

from pipeline.core.codedeps import ROOT, module_closure
from pipeline.params import load_params
from pipeline.params.plan import plan_text

STAGES = yaml.safe_load(plan_text(EVERY_STAGE))["stages"]


def stage_module(name: str) -> str:
    """The module planned stage `name` runs, from its cmd's `mapex <command>`."""
    return "stages." + re.match(r"mapex ([\w-]+)", STAGES[name]["cmd"]).group(1).replace("-", "_")


def test_the_committed_dvc_yaml_is_the_plan_of_params_yaml():
    """dvc.yaml is what `mapex plan` writes for params.yaml, byte for byte (fix: `mapex plan`)."""
    text = (ROOT / "dvc.yaml").read_text()
    assert text == plan_text(load_params(ROOT / "params.yaml")), "dvc.yaml is not params.yaml's plan: run `mapex plan`"


def code_deps(stage: dict) -> set[str]:
    return {d for d in stage.get("deps", []) if d.startswith(("pipeline/", "stages/"))}


@pytest.mark.parametrize("name", sorted(STAGES))
def test_stage_code_deps_are_its_import_closure(name):
    expected = set(module_closure(stage_module(name))) | {"stages/cli.py"}
    got = code_deps(STAGES[name])
    assert not expected - got, f"planned stage {name} misses deps {sorted(expected - got)}"
    assert not got - expected, f"planned stage {name} lists deps it does not import {sorted(got - expected)}"


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


def test_closure_follows_from_imports_and_package_inits(tmp_path):
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
    assert cd.module_closure("pipeline.top", Path(tmp_path)) == (  # a project root of its own
        "pipeline/__init__.py",
        "pipeline/sub/__init__.py",
        "pipeline/sub/leaf.py",
        "pipeline/top.py",
    )


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


# What produced a run (pipeline.core.provenance) is a file of its own: `--provenance RECORD`, an out
# of the stage at data/provenance/<its --out below data/>.json, which no stage reads but the report.
# The fidelity checks write metrics that nothing downstream reads, and record nothing.
UNRECORDED = {"critic_fidelity", "critic_fidelity_posthoc"}


def option(stage: dict, name: str) -> str | None:
    found = re.findall(rf"--{name} (\S+)", stage["cmd"])
    assert len(found) <= 1, f"{name} given twice in {stage['cmd']!r}"
    return found[0] if found else None


def inside(path: str, folder: str) -> bool:
    return path == folder or path.startswith(folder.rstrip("/") + "/")


def out_paths(stage: dict) -> list[str]:
    return [o if isinstance(o, str) else next(iter(o)) for o in stage.get("outs", [])]


@pytest.mark.parametrize("name", sorted(set(STAGES) - {"report"}))
def test_provenance_record_is_an_out_of_its_own_that_only_the_report_reads(name):
    stage = STAGES[name]
    record = option(stage, "provenance")
    if name in UNRECORDED:
        assert record is None, f"stage {name}: records provenance; take it out of UNRECORDED"
        return
    assert record is not None, f"stage {name}: no --provenance in its cmd"
    out = option(stage, "out")
    outs = out_paths(stage)
    # a stage writing one objective's slot below its --out (train_specialist_imported: --out is the
    # seed's folder, as for train_specialist) records beside that slot, as import_specialist does
    out = next((o for o in outs if o == out + "/obj${item.objective}"), out)
    assert out.startswith("data/") and record == f"data/provenance/{out[len('data/') :]}.json", (name, record)
    assert record in outs, f"stage {name}: its record {record} is no out"
    assert not [o for o in outs if o != record and inside(record, o)], f"stage {name}: record inside another out"
    readers = [n for n, s in STAGES.items() if n != "report" and any(inside(record, d) for d in s.get("deps", []))]
    assert not readers, f"{record} is read by {readers}: a rerun that changes no number would rerun them"


def test_the_report_reads_the_records_its_table_shows():
    from pipeline.reporting.runs import PROVENANCE_FOLDERS

    report = STAGES["report"]
    assert option(report, "provenance") == "data/provenance"
    for folder in PROVENANCE_FOLDERS.values():
        assert f"data/provenance/{folder}" in report["deps"], folder
    # every stage that writes data/<folder>/METHOD/seedS records under data/provenance/<folder>
    writers = [option(s, "out") or "" for s in STAGES.values()]
    for folder in PROVENANCE_FOLDERS.values():
        assert any(w.startswith(f"data/{folder}/") for w in writers), folder


def test_provenance_check_sees_a_record_read_downstream():
    """The checks above are not blind: a record inside a folder another stage reads is caught."""
    assert inside("data/specialists/td3/seed0/provenance.json", "data/specialists/td3/seed0")
    assert not inside("data/provenance/specialists/td3/seed0.json", "data/specialists/td3/seed0")
    assert option({"cmd": "mapex x --out data/a --provenance data/provenance/a.json"}, "provenance") == (
        "data/provenance/a.json"
    )


def test_the_plan_puts_each_stages_deps_last_and_keeps_what_follows_the_stages():
    """dvc.yaml for readers: matrix, cmd, params and outs first, then deps (data deps, then the
    planned code deps); the top-level key after `stages:` (plots:) stays where it is."""
    from pipeline.params.plan import CODE_MARKER

    text = plan_text(EVERY_STAGE)
    planned = yaml.safe_load(text)
    assert list(planned) == ["stages", "plots"]
    for name, stage in planned["stages"].items():
        assert list(stage)[-1] == "deps", name
        code = [d for d in stage["deps"] if d.startswith(("pipeline/", "stages/"))]
        assert stage["deps"][-len(code) :] == code == sorted(code), name  # data deps first, code sorted
    assert text.count(CODE_MARKER) == len(planned["stages"])
    assert plan_text(EVERY_STAGE) == text  # the same params give the same plan


def _listed(stage: str, section: str) -> list[str]:
    """The keys of params section `section` stage `stage` lists one by one (`section` itself: '*')."""
    out = []
    for p in STAGES[stage]["params"]:
        if p == section:
            out.append("*")
        elif isinstance(p, str) and p.startswith(section + "."):
            out.append(p.split(".", 1)[1])
    return out


def test_stages_list_exactly_the_section_keys_they_read():
    """DVC reruns a stage when a param it lists changes: the stages that read part of a section
    list those keys, from the tables their code reads (so `td3.shared_init`, read by the TD3
    specialists only, reruns nothing of PDERL or MOPDERL, and `extract.beta` no warm-up-only front)."""
    from pipeline.params.extract import WARMUP_ONLY_KEYS
    from pipeline.params.interpolate import INTERPOLATE_EXTRACT_KEYS
    from pipeline.params.td3 import AGENT_KEYS

    for stage in ("train_pderl", "mopderl"):
        assert _listed(stage, "td3") == list(AGENT_KEYS), stage
        assert not {"shared_init", "shared_prefix_steps", "shared_prefix_weights"} & set(AGENT_KEYS)
    for stage in ("train_specialist", "train_specialist_imported", "train_specialist_variant"):
        assert _listed(stage, "td3") == ["*"], stage  # shared_init is theirs
    assert _listed("warmup_only_td3", "extract") == list(WARMUP_ONLY_KEYS)
    for stage in ("interpolate_td3", "interpolate_td3_halfway"):
        assert _listed(stage, "extract") == list(INTERPOLATE_EXTRACT_KEYS), stage
    # a variant's stage tracks its own overrides, by its name (pipeline/params/variants.py)
    assert "variants.mapex_td3_wide" in STAGES["mapex_td3_wide"]["params"]
    assert "variants.interpolate_td3_halfway" in STAGES["interpolate_td3_halfway"]["params"]
    assert not any(str(p).startswith("variants.") for p in STAGES["mapex_td3"]["params"])
    assert "variants.${item.spec}" in STAGES["train_specialist_variant"]["params"]
