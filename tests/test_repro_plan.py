"""`mapex repro PLAN` with a preset or a grid (pipeline/distributed/onebox.py, stages/repro.py):
the plan file read as a grid (a preset as a grid of one cell), the cells' stage items merged
into one schedule that runs an item two cells share once, the option rules, and (slow tier) a
grid of two cells run on this machine with no Ray and no remote: the first cell's dvc.lock equals
a serial `dvc repro` of the same params, the second restores what it shares from the checkout's
DVC cache, and a second run runs nothing.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from support.tiny_params import TINY_CHAIN as TINY
from support.tiny_params import save_params
from test_sweep import source  # noqa: F401  (the fixture: a git + DVC copy of the code with the tiny params)
from typer.testing import CliRunner

from pipeline.distributed.errors import GridError
from pipeline.distributed.grid import load_grid, plan_cells
from pipeline.distributed.onebox import CellItems, load_plan, merged_items
from pipeline.distributed.workspace import StageItem, checkout_cell
from stages.repro import split_plan

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


def item(name: str, signature: str, *upstream: str) -> StageItem:
    return StageItem(name, name.split("@")[0], tuple(upstream), (), signature)


def test_a_first_yaml_argument_is_the_plan_and_the_rest_are_targets():
    assert split_plan([]) == (None, [])
    assert split_plan(["report", "score@0"]) == (None, ["report", "score@0"])
    assert split_plan(["grid.yml", "report"]) == (Path("grid.yml"), ["report"])


def test_a_preset_is_a_grid_of_one_cell_and_a_grid_is_itself(tmp_path):
    (tmp_path / "presets").mkdir()
    preset = tmp_path / "presets" / "mine.yaml"
    preset.write_text(yaml.safe_dump({"env": {"id": "mo-hopper-2obj-v5"}, "seeds": [0]}))
    grid, name = load_plan(preset, tmp_path)
    assert name == "mine" and [e.preset for e in grid.envs] == ["presets/mine.yaml"]
    gfile = tmp_path / "g.yaml"
    gfile.write_text(yaml.safe_dump({"envs": ["mo-swimmer-v5"], "seeds": [1, 2]}))
    grid, name = load_plan(gfile, tmp_path)
    assert name == "g" and grid.envs[0].id == "mo-swimmer-v5" and grid.seeds == [1, 2]


def test_bad_plan_files_are_named(tmp_path):
    with pytest.raises(GridError, match=r"nothere\.yaml: plan file .* not found"):
        load_plan(tmp_path / "nothere.yaml", tmp_path)
    listy = tmp_path / "list.yaml"
    listy.write_text("- a\n- b\n")
    with pytest.raises(GridError, match=r"list\.yaml: expected a mapping"):
        load_plan(listy, tmp_path)
    outside = tmp_path / "out.yaml"
    outside.write_text("seeds: [0]\n")
    inside = tmp_path / "repo"
    inside.mkdir()
    with pytest.raises(GridError, match=r"out\.yaml: a preset must lie inside the checkout"):
        load_plan(outside, inside)


def test_merged_items_share_one_computation_between_cells_and_interleave_them():
    a = CellItems(
        "a", Path("/w/a"), [item("train@0", "T"), item("extract@0", "Ea", "train@0"), item("report", "Ra", "extract@0")]
    )
    b = CellItems(
        "b", Path("/w/b"), [item("train@0", "T"), item("extract@0", "Eb", "train@0"), item("report", "Rb", "extract@0")]
    )
    items, places = merged_items([a, b])
    assert [i.name for i in items] == ["a/train@0", "b/train@0", "a/extract@0", "b/extract@0", "a/report", "b/report"]
    by = {i.name: i for i in items}
    # b's specialists are a's computation: they wait for a's and are then restored, not computed
    assert by["b/train@0"].upstream == ("a/train@0",)
    assert by["b/extract@0"].upstream == ("b/train@0",)
    assert by["a/report"].upstream == ("a/extract@0",)
    assert places["b/extract@0"] == (Path("/w/b"), "extract@0")


def cli(*args: str):
    import typer

    from stages.repro import repro

    app = typer.Typer(add_completion=False)

    @app.callback()
    def main() -> None:
        pass

    app.command("repro")(repro)
    return CliRunner().invoke(app, ["repro", *args])


def test_option_rules_are_one_line_errors(tmp_path):
    grid = tmp_path / "g.yaml"
    grid.write_text(yaml.safe_dump({"envs": ["mo-swimmer-v5"]}))
    r = cli(str(grid), "--ray", "local")
    assert r.exit_code == 2 and "--ray and --remote go together" in r.output
    r = cli("--seed", "1", "--root", str(tmp_path))
    assert r.exit_code == 2 and "go with a preset or grid PLAN" in r.output
    # the cluster options (what `mapex sweep` had) are named when given without --ray
    r = cli(str(grid), "--workers", "2", "--dry-run", "--max-retries", "1")
    assert r.exit_code == 2 and "--workers, --max-retries, --dry-run go with --ray" in r.output
    r = cli(str(grid), "--ray", "auto", "--remote", str(tmp_path / "r"), "--workers", "2")
    assert r.exit_code == 2 and "--workers sizes a local Ray cluster (--ray local)" in r.output
    r = cli(str(grid), "--ray", "local", "--remote", str(tmp_path / "r"), "--remote-option", "endpointurl")
    assert r.exit_code == 2 and "--remote-option 'endpointurl': expected KEY=VALUE" in r.output


# ------------------------------------------------------------------------------------------
# A grid on this machine, through real DVC (slow tier)


def git(cwd: Path, *args: str) -> str:
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True, text=True).stdout.strip()


def mapex(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ['PATH']}", "MAPEX_TORCH_THREADS": "1"}
    return subprocess.run([str(BIN / "mapex"), *args], cwd=cwd, env=env, capture_output=True, text=True)


@pytest.mark.slow  # two cells of the tiny pipeline and a serial dvc repro: `make test-slow` (CI runs it)
def test_a_grid_runs_here_bitwise_as_serial_dvc_repro_and_shares_its_runs(source, tmp_path):  # noqa: F811
    from test_sweep import without_measured

    grid = {
        "envs": ["mo-hopper-2obj-v5"],
        "seeds": [0],
        "overrides": {"a": {}, "b": {"critic_fidelity": {"episodes": 3}}},
    }
    path = tmp_path / "two.yaml"
    path.write_text(yaml.safe_dump(grid, sort_keys=False))
    commit = git(source, "rev-parse", "HEAD")
    cell_a = plan_cells(load_grid(path), path, source, commit)[0]
    serial = tmp_path / "serial"
    git(tmp_path, "clone", "-q", str(source), str(serial))
    checkout_cell(serial, commit, cell_a.params_text)
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ['PATH']}", "PYTHONPATH": str(serial)}
    env["MAPEX_TORCH_THREADS"] = "1"
    with open(tmp_path / "serial.log", "w") as log:
        proc = subprocess.Popen([str(BIN / "dvc"), "repro"], cwd=serial, env=env, stdout=log, stderr=subprocess.STDOUT)
        try:
            r = mapex(["repro", str(path), "--jobs", "2", "--workdir", str(tmp_path / "work")], source)
        finally:
            rc = proc.wait()
    assert rc == 0, (tmp_path / "serial.log").read_text()[-3000:]
    assert r.returncode == 0, r.stderr[-4000:]
    work = tmp_path / "work"
    a, b = work / "mo-hopper-2obj-v5.a", work / "mo-hopper-2obj-v5.b"
    assert without_measured((a / "dvc.lock").read_text()) == without_measured((serial / "dvc.lock").read_text())
    # b differs only in critic_fidelity.episodes: its specialists and extraction are a's, restored
    assert re.search(r"restored\s+mo-hopper-2obj-v5\.b/train_specialist@0", r.stderr), r.stderr[-3000:]
    assert re.search(r"ran\s+mo-hopper-2obj-v5\.b/critic_fidelity@0", r.stderr), r.stderr[-3000:]
    la, lb = (yaml.safe_load((w / "dvc.lock").read_text())["stages"] for w in (a, b))
    assert la["train_specialist@0"] == lb["train_specialist@0"]
    assert (work / "report" / "report.md").is_file()  # the cross-cell report of the two cells
    assert not (source / "data").exists()  # the checkout's own workspace is left alone
    again = mapex(["repro", str(path), "--jobs", "2", "--workdir", str(work)], source)
    assert again.returncode == 0, again.stderr[-3000:]
    assert again.stderr.count("up to date, nothing to run") == 2


def test_a_stale_plan_is_planned_again_before_it_runs(tmp_path, capsys):
    from pipeline.params import load_params
    from pipeline.params.plan import write_plan
    from pipeline.params.planned import stale_input
    from stages.repro import _replan_if_stale

    params = save_params(tmp_path / "params.yaml", TINY, sort_keys=False)
    write_plan(load_params(params, check_plan=False), params)
    before = (tmp_path / "dvc.yaml").read_text()
    _replan_if_stale(tmp_path)  # current: untouched, nothing said
    assert (tmp_path / "dvc.yaml").read_text() == before and capsys.readouterr().err == ""
    raw = yaml.safe_load(params.read_text())
    raw["seeds"] = [0, 1]
    params.write_text(yaml.safe_dump(raw, sort_keys=False))
    assert stale_input(raw, before) is not None
    _replan_if_stale(tmp_path)
    after = (tmp_path / "dvc.yaml").read_text()
    assert after != before and stale_input(raw, after) is None
    assert "planned again" in capsys.readouterr().err


def test_a_preset_for_ray_is_written_as_a_one_cell_grid_file(tmp_path):
    from stages.repro import _one_cell_grid

    (tmp_path / "presets").mkdir()
    preset = tmp_path / "presets" / "mine.yaml"
    preset.write_text("seeds: [0]\n")
    path = _one_cell_grid(preset, tmp_path)
    assert path.parent == tmp_path / ".dvc" / "tmp" / "mapex-repro"
    assert [e.preset for e in load_grid(path).envs] == ["presets/mine.yaml"]
