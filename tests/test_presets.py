"""The shipped params files (quickstart, the paper presets, the payoff preset) validate, resolve in
dvc.yaml and match the paper."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from pipeline.evaluation.reference_points import TABLE, resolve_reference_point
from pipeline.params import KNOWN_SECTIONS, RUN_KEYS, EnvParams, load_params, section
from pipeline.params.env_facts import paper_extract, paper_extract_envs, reference_points
from pipeline.params.extract import ExtractParams
from pipeline.params.plan import plan_text
from pipeline.params.registry import section_models
from pipeline.params.td3 import TD3Params
from pipeline.params.tracked import tidied_text
from pipeline.params.train_pderl import TrainPderlParams
from pipeline.params.train_specialist import TrainSpecialistParams, check_against_td3

ROOT = Path(__file__).resolve().parents[1]
PRESETS = sorted((ROOT / "presets" / "paper").glob("*.yaml"))


PAYOFF = ROOT / "presets" / "payoff" / "mo-halfcheetah-v5.yaml"
# Three objectives (docs/n_objectives.md): paper-scale and quickstart-scale, mo-hopper-v5 and mo-ant-v5
NOBJ = sorted((ROOT / "presets" / "nobj").glob("*.yaml"))
# Bring your own specialists: every objective imported, and one imported with the other trained here
IMPORTED = [ROOT / "presets" / "imported.yaml", ROOT / "presets" / "mixed.yaml"]
# The studies of docs/results.md: sweep grids over the presets (not params files)
STUDIES = sorted((ROOT / "presets" / "studies").glob("*.yaml"))
# Every params file shipped: params.yaml and every preset (envs.yaml is the per-env facts, not one;
# presets/studies/ holds grids and, under evidence/, what past runs used: not presets)
SHIPPED = [p for p in sorted((ROOT / "presets").rglob("*.yaml")) if "studies" not in p.relative_to(ROOT).parts]
ALL_PARAMS = [ROOT / "params.yaml"] + [p for p in SHIPPED if p.name != "envs.yaml"]


@pytest.mark.parametrize("path", ALL_PARAMS, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_params_file_validates(path, tmp_path):
    """params.yaml as it is; a preset as `mapex plan --from` writes it (presets list
    what runs once, in `methods`). Every section validates with its model (no key left where
    it moved from: load_params refuses that), and so does the check across td3 and
    train_specialist that stage train_specialist makes."""
    if path != ROOT / "params.yaml":
        (tmp_path / "params.yaml").write_text(tidied_text(path.read_text(), str(path)))
        path = tmp_path / "params.yaml"
    raw = load_params(path)
    env = section(raw, "env", EnvParams, path)
    for name, model in section_models().items():
        section(raw, name, model, path)
    check_against_td3(
        section(raw, "train_specialist", TrainSpecialistParams, path), section(raw, "td3", TD3Params, path)
    )
    # its own point, or (null) the env's entry in the table, one value per objective
    resolve_reference_point(env.reference_point, env.id, len(raw["objectives"]), path, ROOT / TABLE)


def test_every_params_file_is_checked():
    """ALL_PARAMS holds the files the tests above name one by one, and then some."""
    assert {ROOT / "params.yaml", *PRESETS, PAYOFF, *NOBJ, *IMPORTED} <= set(ALL_PARAMS)


def test_every_known_section_has_a_model():
    assert set(KNOWN_SECTIONS) == (set(section_models()) - {""}) | set(RUN_KEYS)


def test_paper_presets_cover_the_five_envs_with_the_paper_settings():
    assert {p.stem for p in PRESETS} == set(paper_extract_envs())
    for path in PRESETS:
        raw = load_params(path)
        env = section(raw, "env", EnvParams, path)
        ex = section(raw, "extract", ExtractParams, path).resolved(env.id)
        assert (ex.epochs, ex.beta, ex.omega_max) == paper_extract(env.id)
        assert (ex.iterations, ex.child_buffer_size, ex.eval_episodes, ex.warmup_steps) == (1200, 200_000, 5, 1000)
        ts = section(raw, "train_specialist", TrainSpecialistParams, path)
        assert ts.total_steps == (1_000_000 if env.id == "mo-swimmer-v5" else 2_000_000)
        assert ts == TrainSpecialistParams(total_steps=ts.total_steps)  # everything else: the defaults
        assert section(raw, "td3", TD3Params, path) == TD3Params()  # the paper's TD3 table
        assert env.max_episode_steps == 750


# PDERL's reference code copies the RL actor into the population every generation on Hopper,
# Walker2d and Ant, every 10 generations on the other envs (train_pderl.rl_sync_period).
RL_SYNC_PERIOD = {
    "mo-halfcheetah-v5": 10,
    "mo-swimmer-v5": 10,
    "mo-hopper-2obj-v5": 1,
    "mo-walker2d-v5": 1,
    "mo-ant-2obj-v5": 1,
    "mo-hopper-v5": 1,
    "mo-ant-v5": 1,
}


def test_presets_set_pderls_rl_sync_period_of_their_env():
    """Every preset that configures train_pderl (the five paper presets at least) sets
    rl_sync_period explicitly, to its env's value in PDERL's code: the default, 1, is right
    for three of the five envs only."""
    configured = [p for p in SHIPPED if "train_pderl" in yaml.safe_load(p.read_text())]
    assert set(PRESETS) <= set(configured)
    for path in configured:
        raw = load_params(path)
        env = section(raw, "env", EnvParams, path)
        assert "rl_sync_period" in raw["train_pderl"], path
        assert section(raw, "train_pderl", TrainPderlParams, path).rl_sync_period == RL_SYNC_PERIOD[env.id], path


def test_three_objective_presets():
    """A paper-scale and a quickstart-scale preset for each 3-objective env, all three objectives,
    the reference point of presets/envs.yaml, and extraction values set explicitly
    (the paper has none for these envs); the paper-scale ones carry the paper's budgets. The facets
    preset has the facet rule on, and its variant mapex_td3_every_facet turns it off ("before")."""
    refs = reference_points()
    assert {p.stem for p in NOBJ} == {
        "mo-hopper-v5",
        "mo-hopper-v5-quick",
        "mo-ant-v5",
        "mo-ant-v5-quick",
        "mo-hopper-v5-facets",
    }
    for path in NOBJ:
        raw = load_params(path)
        env = section(raw, "env", EnvParams, path)
        assert env.id == path.stem.removesuffix("-quick").removesuffix("-facets") and raw["objectives"] == [0, 1, 2]
        assert env.reference_point == refs[env.id] and env.max_episode_steps == 750
        assert all(raw["extract"].get(k) is not None for k in ("epochs", "beta", "omega_max")), path
        ts = section(raw, "train_specialist", TrainSpecialistParams, path)
        td3 = section(raw, "td3", TD3Params, path)
        assert td3.secondary_critics
        if path.stem.endswith("-facets"):
            assert raw["extract"]["facet_bridge_ratio"] is not None and ts.total_steps >= 600_000
            # "before" runs on the same specialists without the rule, paired against "after"
            assert raw["variants"]["mapex_td3_every_facet"]["extract"] == {"facet_bridge_ratio": None}
            assert ["mapex_td3", "mapex_td3_every_facet"] in raw["report"]["pairs"]
        elif not path.stem.endswith("-quick"):
            assert ts == TrainSpecialistParams(total_steps=2_000_000)
            assert td3 == TD3Params()
            ex = section(raw, "extract", ExtractParams, path)
            assert (ex.iterations, ex.child_buffer_size, ex.eval_episodes, ex.warmup_steps) == (1200, 200_000, 5, 1000)


@pytest.mark.parametrize(
    "path",
    [ROOT / "params.yaml", *PRESETS, PAYOFF, *NOBJ, *IMPORTED],
    ids=lambda p: f"{p.parent.name}/{p.name}",
)
def test_every_section_a_running_stage_reads_is_in_the_file(path, tmp_path):
    """DVC refuses to run a stage whose params section is missing from params.yaml (it does not
    fall back to the defaults the stage itself would take): every params key a stage of this
    file's plan lists must be in it."""
    text = tidied_text(path.read_text(), str(path))
    raw = yaml.safe_load(text)
    stages = yaml.safe_load(plan_text(raw))["stages"]  # only the stages that run here
    missing = {}
    for name, stage in stages.items():
        for dep in stage.get("params", []):
            if isinstance(dep, dict):
                (file, keys), *_ = dep.items()
                assert file == "presets/envs.yaml", dep  # the per-env facts: one file for every params file
                facts = yaml.safe_load((ROOT / file).read_text())
                missing_keys = [f"{file}:{k}" for k in keys if k not in facts]
            else:
                missing_keys = [dep] if not _has_key(raw, dep) and "${" not in dep else []
            if missing_keys:
                missing.setdefault(name, []).extend(missing_keys)
    assert not missing, f"{path}: stages whose params are missing: {missing}"


def _has_key(raw: dict, dotted: str) -> bool:
    """Whether params `raw` holds key path `dotted` (`extract.beta`): what DVC requires of a listed param."""
    node = raw
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            return False
        node = node[part]
    return True


def test_payoff_preset_is_the_issue_settings():
    """300k-step specialists at 256 units, 2 seeds; paper-form children (HalfCheetah: 20 epochs, beta 1,
    omega_max 1) on 200k-row hybrid buffers at 256 units, at least 12 each, one per iteration."""
    raw = load_params(PAYOFF)
    ts = section(raw, "train_specialist", TrainSpecialistParams, PAYOFF)
    td3 = section(raw, "td3", TD3Params, PAYOFF)
    assert ts.total_steps >= 300_000 and td3.hidden_sizes == [256, 256] and td3.secondary_critics
    assert len(raw["seeds"]) >= 2
    ex = section(raw, "extract", ExtractParams, PAYOFF).resolved("mo-halfcheetah-v5")
    assert (ex.epochs, ex.beta, ex.omega_max) == paper_extract("mo-halfcheetah-v5")
    assert ex.iterations * ex.children_per_iteration >= 12 and ex.children_per_iteration == 1
    assert (ex.child_buffer_size, ex.hidden_sizes) == (200_000, [256, 256])


@pytest.mark.parametrize(
    "path", [ROOT / "params.yaml", *PRESETS, PAYOFF, *NOBJ], ids=lambda p: f"{p.parent.name}/{p.name}"
)
def test_dvc_resolves_the_pipeline_of_every_params_file(path, tmp_path):
    """`dvc stage list` with dvc.yaml and the params file: its matrices resolve, and every
    method x seed of `methods` gets an evaluate and a score item."""
    dvc = Path(sys.executable).parent / "dvc"
    if not dvc.is_file():
        pytest.fail(f"dvc is not installed next to {sys.executable}")
    # as `mapex plan --from` writes them: the params file and the dvc.yaml planned for it
    (tmp_path / "params.yaml").write_text(tidied_text(path.read_text(), str(path)))
    (tmp_path / "dvc.yaml").write_text(plan_text(load_params(tmp_path / "params.yaml")))
    subprocess.run(["git", "init", "-q"], cwd=tmp_path, check=True)
    subprocess.run([str(dvc), "init", "-q"], cwd=tmp_path, check=True)
    r = subprocess.run([str(dvc), "stage", "list", "--name-only"], cwd=tmp_path, capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    items = set(r.stdout.split())
    raw = yaml.safe_load(path.read_text())
    for stage in ("evaluate", "score"):
        assert {i for i in items if i.startswith(stage + "@")} == {
            f"{stage}@{s}-{m}" for s in raw["seeds"] for m in raw["methods"]
        }
    assert "report" in items


@pytest.mark.parametrize("path", STUDIES, ids=lambda p: p.stem)
def test_study_grid_plans_its_cells(path):
    """Each study grid names its command in its header and expands, at the repository's HEAD (what
    `mapex repro --ray` runs), into cells whose params validate with the stages' models; every method a
    cell lists is reported, and every pair the report compares is of methods the cell runs."""
    from pipeline.distributed.grid import load_grid, plan_cells

    header = path.read_text().split("\n", 1)[0]
    assert header.startswith("# Study (docs/results.md"), f"{path}: the first line names the results section"
    text = path.read_text()  # its command: `mapex repro GRID` (here, or on Ray with --ray)
    assert f"mapex repro presets/studies/{path.name}" in text
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True)
    cells = plan_cells(load_grid(path), path, ROOT, head.stdout.strip())
    assert cells, path
    for cell in cells:
        methods = cell.params["methods"]
        for pair in (cell.params.get("report") or {}).get("pairs") or []:
            assert set(pair) <= set(methods), f"{path}: cell {cell.name} pairs {pair}, not all in {methods}"


def test_the_studies_of_the_results_have_grids():
    """docs/results.md's studies each have a grid (the harness that ran them is gone)."""
    assert {p.stem for p in STUDIES} >= {"answer64", "answer256", "hopper64", "facets", "payoff", "mixed"}
    # issue 44's study, "Is the hybrid ahead?" (results section 2.6)
    assert {p.stem for p in STUDIES} >= {"front64", "front256", "fronthopper", "frontmixed"}


def cells(name: str) -> dict[str, dict]:
    """The cells of study grid presets/studies/<name>.yaml at HEAD: cell name -> its params."""
    from pipeline.distributed.grid import load_grid, plan_cells

    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True)
    path = ROOT / "presets" / "studies" / f"{name}.yaml"
    return {c.name: c.params for c in plan_cells(load_grid(path), path, ROOT, head.stdout.strip())}


def test_the_mixed_preset_runs_the_form_measured_best_and_section_8_keeps_its_own():
    """Issue 44, item 5: presets/mixed.yaml's MAPEX-PostHoc is the hybrid exactly as its study's
    `hybrid` cell ran it (results 2.6.4: ahead of the paper form, warm-up only and interpolation
    in every seed), beside both baselines; section 8's grid still runs the gentle paper form."""
    preset = load_params(ROOT / "presets" / "mixed.yaml")
    measured = cells("frontmixed")["halfcheetah-mixed.hybrid"]
    assert preset["extract"] == measured["extract"]
    assert preset["extract"]["init"] == "interpolate" and preset["extract"]["seed_interpolation"] == 12
    assert preset["methods"] == measured["methods"]
    (section8,) = cells("mixed").values()
    assert section8["methods"] == ["mapex_posthoc_imported", "warmup_only_imported"]
    ext = section8["extract"]
    assert (ext["init"], ext["seed_interpolation"], ext["epochs"], ext["lr"]) == ("warmup", 0, 1, 0.0001)


def test_the_hybrid_studies_compare_four_methods_on_equal_children():
    """Issue 44's grids run the hybrid, the paper form, warm-up only and interpolation from the same
    specialists, the hybrid seeded with as many interpolated policies as the paper form trains
    children, and pair the hybrid with each; the answer grids over the same presets still leave the
    hybrid out. The mixed-source case, whose method has no variants, is two cells that differ only
    in the hybrid's extract keys (so everything else is one run each, shared)."""

    def seeded(ext: dict) -> dict:
        return {"init": "interpolate", "seed_interpolation": ext["iterations"] * ext["children_per_iteration"]}

    for name in ("front64", "front256", "fronthopper"):
        (params,) = cells(name).values()
        assert params["methods"] == ["mapex_td3", "hybrid_td3", "warmup_only_td3", "interpolate_td3"], name
        hybrid = params["variants"]["hybrid_td3"]
        assert hybrid["of"] == "mapex_td3" and hybrid["extract"] == seeded(params["extract"]), name
        pairs = {tuple(p) for p in params["report"]["pairs"]}
        assert {("hybrid_td3", b) for b in ("mapex_td3", "interpolate_td3", "warmup_only_td3")} <= pairs, name
    for name in ("answer256", "hopper64"):
        assert all("hybrid_td3" not in params["methods"] for params in cells(name).values()), name
    mixed = cells("frontmixed")
    paper, hybrid = mixed["halfcheetah-mixed.paper"], mixed["halfcheetah-mixed.hybrid"]
    assert paper["methods"] == ["mapex_posthoc_imported", "warmup_only_imported", "interpolate_imported"]
    ext = paper["extract"]
    assert ext["init"] == "warmup" and ext["seed_interpolation"] == 0  # the paper's start
    assert ext["epochs"] == paper_extract("mo-halfcheetah-v5")[0] and ext["lr"] == 0.0003
    assert hybrid["extract"] == ext | seeded(ext)
    assert {k: v for k, v in hybrid.items() if k != "extract"} == {k: v for k, v in paper.items() if k != "extract"}
    # hybrid vs paper form crosses the cells: the grid report's --pair, as the grid's header and
    # results 2.6 give it, names these two cells and the method they both run
    for doc in (ROOT / "presets" / "studies" / "frontmixed.yaml", ROOT / "docs" / "results.md"):
        (pair,) = re.findall(r"--pair ([\w.\-/,]+)", doc.read_text()) or [None]
        sides = [side.partition("/") for side in (pair or "").split(",")]
        assert [(c, m) for c, _, m in sides] == [
            ("halfcheetah-mixed.hybrid", "mapex_posthoc_imported"),
            ("halfcheetah-mixed.paper", "mapex_posthoc_imported"),
        ], doc
        assert all(m in mixed[c]["methods"] for c, _, m in sides), doc
