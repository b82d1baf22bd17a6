"""`mapex repro GRID --ray` (pipeline/distributed/) on a local two-node Ray cluster and a local-directory DVC
remote, with the real dvc.yaml on a tiny preset in a temporary git + DVC copy of the project.

Checks: grid files are validated with errors naming file and key; the DAG and each cell's
workspace come from DVC; a sweep whose worker dies mid-task (after its stage ran, before it
published anything) still completes, and the cell's dvc.lock equals a serial `dvc repro` of that
cell (every hash, but those of the provenance records and the report: they hold measured seconds); a second sweep runs nothing; a grid of two envs whose one cell shares
its runs with the first sweep restores them from the remote's run-cache instead of computing.
"""

from __future__ import annotations

import os
import re
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import typer
import yaml
from support.tiny_params import TINY_CHAIN as TINY
from support.tiny_params import save_params
from typer.testing import CliRunner

from pipeline.distributed.driver import _resources, stage_processes
from pipeline.distributed.errors import GridError
from pipeline.distributed.grid import Grid, load_grid, plan_cells
from pipeline.distributed.task import DIE_ONCE_ENV, StageTask, task_resume_dir
from pipeline.distributed.workspace import checkout_cell, stage_items
from pipeline.params.plan import write_plan
from stages.repro import repro

# Sweeps through Ray and DVC in a temporary repository: `make test-fast` leaves this file out.
pytestmark = pytest.mark.integration

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent

# The first sweep the Ray tests run: the whole pipeline (14 stage items) of one cell.
GRID = {"envs": ["mo-hopper-2obj-v5"], "seeds": [0]}
DIES = "mo-hopper-2obj-v5/mapex_td3@0"  # this task's worker dies once, after its stage ran


def git(cwd: Path, *args: str) -> str:
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True, text=True).stdout.strip()


def write_grid(path: Path, grid: dict) -> Path:
    path.write_text(yaml.safe_dump(grid, sort_keys=False))
    return path


@pytest.fixture(scope="module")
def source(tmp_path_factory) -> Path:
    """A git + DVC repository holding the project's code, dvc.yaml and the tiny params."""
    root = tmp_path_factory.mktemp("source")
    for name in ("pipeline", "stages"):
        shutil.copytree(ROOT / name, root / name, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(ROOT / "dvc.yaml", root / "dvc.yaml")
    (root / "presets").mkdir()
    shutil.copy(ROOT / "presets" / "envs.yaml", root / "presets" / "envs.yaml")
    save_params(root / "params.yaml", TINY, sort_keys=False)
    # valid params (objectives has a default), but dvc.yaml's stages list the key itself (DVC refuses it missing)
    (root / "no_objectives.yaml").write_text(
        yaml.safe_dump({k: v for k, v in TINY.items() if k != "objectives"}, sort_keys=False)
    )
    (root / ".gitignore").write_text("/data/\n__pycache__/\nMUJOCO_LOG.TXT\n/sweeps/\n")
    git(root, "init", "-q")
    git(root, "config", "user.email", "test@example.com")
    git(root, "config", "user.name", "test")
    subprocess.run([str(BIN / "dvc"), "init", "-q"], cwd=root, check=True)
    git(root, "add", "-A")
    git(root, "commit", "-qm", "tiny pipeline")
    return root


def cli_app() -> typer.Typer:
    app = typer.Typer(add_completion=False)

    @app.callback()
    def main() -> None:  # a group, so the command is invoked by name as under `mapex`
        pass

    app.command("repro")(repro)
    return app


def run_cli(grid, *args) -> "typer.testing.Result":
    """`mapex repro GRID --ray local ARGS` (the Ray run; --repo of ARGS is its --root). A cluster the
    test started is found already initialised, as a driver inside a Ray job finds its own."""
    args = ["--root" if a == "--repo" else str(a) for a in args]
    return CliRunner().invoke(cli_app(), ["repro", str(grid), "--ray", "local", *args])


# ------------------------------------------------------------------------------------------
# Without Ray: grid validation, cells, workspaces and the DAG


def test_grid_errors_name_file_and_key(tmp_path, source):
    commit = git(source, "rev-parse", "HEAD")

    def plan(grid: dict):
        path = write_grid(tmp_path / "grid.yaml", grid)
        return plan_cells(load_grid(path), path, source, commit)

    with pytest.raises(GridError, match=r"grid.yaml: invalid grid:\n[\s\S]*  env: unknown key"):
        plan({"env": ["mo-hopper-2obj-v5"]})
    with pytest.raises(GridError, match=r"envs: required key is missing"):
        plan({"seeds": [0]})
    with pytest.raises(GridError, match=r"seeds = \[0, 0\]"):
        plan({"envs": ["mo-hopper-2obj-v5"], "seeds": [0, 0]})
    with pytest.raises(GridError, match=r"envs.0.params = 3: Input should be a valid dictionary"):
        plan({"envs": [{"id": "mo-hopper-2obj-v5", "params": 3}]})
    with pytest.raises(GridError, match=r"resources.extract.gpus"):
        plan({"envs": ["mo-hopper-2obj-v5"], "resources": {"extract": {"gpus": -1}}})
    with pytest.raises(GridError, match=r"envs.0.preset: presets/paper/nope.yaml is not in commit"):
        plan({"envs": ["presets/paper/nope.yaml"]})
    # a params value the stages would reject is caught before anything runs, naming cell and key
    with pytest.raises(GridError, match=r"cell mo-hopper-2obj-v5.bad: invalid params:\n  extract.iterations = -1"):
        plan({"envs": ["mo-hopper-2obj-v5"], "overrides": {"ok": {}, "bad": {"extract": {"iterations": -1}}}})
    with pytest.raises(GridError, match=r"cells \['mo-hopper-2obj-v5'\] appear more than once"):
        plan({"envs": ["mo-hopper-2obj-v5", {"id": "mo-hopper-2obj-v5", "params": {"seeds": [1]}}]})
    with pytest.raises(GridError, match="grid file not found"):
        load_grid(tmp_path / "missing.yaml")
    # through the command: one line on stderr, exit 2
    path = write_grid(tmp_path / "grid.yaml", {"envs": ["mo-hopper-2obj-v5"], "sedes": [0]})
    result = run_cli(path, "--remote", tmp_path / "remote", "--repo", source, "--dry-run")
    assert result.exit_code == 2
    assert "sedes: unknown key" in result.output


def test_cells_merge_presets_overrides_and_seeds(tmp_path, source):
    commit = git(source, "rev-parse", "HEAD")
    grid = {
        "envs": [
            {"name": "cheetah", "id": "mo-halfcheetah-v5", "params": {"extract": {"iterations": 3}}},
            "mo-hopper-2obj-v5",
        ],
        "seeds": [1, 2],
        "overrides": {
            "joint": {},
            "posthoc": {"methods": ["mapex_posthoc_td3"]},
        },
    }
    path = write_grid(tmp_path / "grid.yaml", grid)
    cells = {c.name: c.params for c in plan_cells(load_grid(path), path, source, commit)}
    assert list(cells) == ["cheetah.joint", "cheetah.posthoc", "mo-hopper-2obj-v5.joint", "mo-hopper-2obj-v5.posthoc"]
    assert cells["cheetah.joint"]["extract"]["iterations"] == 3
    assert cells["cheetah.joint"]["extract"]["beta"] == TINY["extract"]["beta"]  # the rest of the base stays
    assert (
        cells["cheetah.posthoc"]["methods"] == ["mapex_posthoc_td3"]
        and cells["cheetah.joint"]["methods"] == TINY["methods"]
    )
    assert cells["mo-hopper-2obj-v5.joint"]["env"]["reference_point"] == [
        -100.0,
        -3390.0,
    ]  # presets/envs.yaml
    assert cells["mo-hopper-2obj-v5.joint"]["extract"]["iterations"] == TINY["extract"]["iterations"]
    assert all(c["seeds"] == [1, 2] for c in cells.values())


def test_seed_option_runs_a_subset_of_the_grids_seeds(tmp_path, source):
    grid = write_grid(tmp_path / "grid.yaml", {"envs": ["mo-hopper-2obj-v5"], "seeds": [1, 2]})
    args = [grid, "--remote", tmp_path / "remote", "--repo", source, "--workdir", tmp_path / "work", "--dry-run"]
    result = run_cli(*args, "--seed", "2")
    assert result.exit_code == 0, result.output
    ws = tmp_path / "work" / "mo-hopper-2obj-v5"
    assert yaml.safe_load((ws / "params.yaml").read_text())["seeds"] == [2]
    first = {i.name: i.signature for i in stage_items(ws)}
    assert "train_specialist@2" in first and not any("@1" in n for n in first)
    # the whole grid later: seed 2's items keep their run-cache keys (restored, not rerun)
    assert run_cli(*args).exit_code == 0
    assert yaml.safe_load((ws / "params.yaml").read_text())["seeds"] == [1, 2]
    whole = {i.name: i.signature for i in stage_items(ws)}
    kept = {n for n in first if "@2" in n and whole[n] == first[n]}
    assert kept == {n for n in first if "@2" in n} and "train_specialist@1" in whole
    result = run_cli(*args, "--seed", "0", "--seed", "0")
    assert result.exit_code == 2 and "--seed [0, 0]: seeds must be unique" in result.output


def test_dry_run_prepares_workspaces_and_reads_the_dag_from_dvc(tmp_path, source):
    grid = write_grid(tmp_path / "grid.yaml", {"envs": ["mo-hopper-2obj-v5"], "seeds": [0]})
    result = run_cli(
        grid, "--remote", tmp_path / "remote", "--repo", source, "--workdir", tmp_path / "work", "--dry-run"
    )
    assert result.exit_code == 0, result.output
    assert "mo-hopper-2obj-v5: planned" in result.output
    ws = tmp_path / "work" / "mo-hopper-2obj-v5"
    # the workspace is a checkout of HEAD's code with the cell's params.yaml (and no dvc.lock)
    assert git(ws, "rev-parse", "HEAD") == git(source, "rev-parse", "HEAD")
    # (and the dvc.yaml planned for them: only the stages the cell runs)
    assert git(ws, "status", "--porcelain", "--untracked-files=no") == "M dvc.yaml\n M params.yaml"
    assert yaml.safe_load((ws / "params.yaml").read_text())["env"]["id"] == "mo-hopper-2obj-v5"
    assert not (ws / "dvc.lock").exists()

    items = {i.name: i for i in stage_items(ws)}
    listed = subprocess.run(
        [str(BIN / "dvc"), "stage", "list", "--name-only"], cwd=ws, capture_output=True, text=True, check=True
    )
    assert set(items) == set(listed.stdout.split())
    assert items["critic_fidelity@0-td3-1"].upstream == ("train_specialist@0",)
    assert items["critic_fidelity@0-td3-1"].pull == ()  # exact output deps: `dvc repro --pull` fetches them
    # the report reads the evaluations, the scores, the extractions' provenance records and the clips
    assert items["report"].upstream == (
        "evaluate@0-mapex_td3",
        "evaluate@0-warmup_only_td3",
        "mapex_td3@0",
        "render",
        "score@0-mapex_td3",
        "score@0-warmup_only_td3",
        "warmup_only_td3@0",
    )
    assert "data/evaluate/mapex_td3/seed0/evaluation.json" in items["report"].pull  # outputs inside its folder deps
    assert "data/score/warmup_only_td3/seed0/metrics.json" in items["report"].pull
    order = list(items)
    assert all(order.index(u) < order.index(n) for n, i in items.items() for u in i.upstream)
    sub = [i.name for i in stage_items(ws, ["mapex_td3@0"])]
    assert sorted(sub) == ["mapex_td3@0", "train_specialist@0"]  # posthoc_from: [] -> no post-hoc fits
    with pytest.raises(ValueError, match="target 'nope' is no stage"):
        stage_items(ws, ["nope"])
    bad = write_grid(
        tmp_path / "bad.yaml", {"envs": ["mo-hopper-2obj-v5"], "seeds": [0], "resources": {"evaluation": {"cpus": 2}}}
    )
    result = run_cli(
        bad, "--remote", tmp_path / "remote", "--repo", source, "--workdir", tmp_path / "work", "--dry-run"
    )
    assert result.exit_code == 2 and "resources: ['evaluation'] are not dvc.yaml stages" in result.output

    # signatures: what DVC's run-cache key depends on besides code. An advantage-weighted extract
    # param changes MAPEX's extraction and everything downstream of it, not the specialists', their
    # critics' fidelity or the warm-up-only ablation's chain (it does not read beta).
    params = yaml.safe_load((ws / "params.yaml").read_text())
    params["extract"]["beta"] = 0.5
    save_params(ws / "params.yaml", params, sort_keys=False)
    changed = {i.name: i for i in stage_items(ws)}
    same = {n for n in items if changed[n].signature == items[n].signature}
    warmup = {"warmup_only_td3@0", "evaluate@0-warmup_only_td3", "score@0-warmup_only_td3"}
    assert same == {"train_specialist@0"} | warmup | {n for n in items if n.startswith("critic_fidelity")}

    # with post-hoc critics on, MAPEX-PostHoc depends on their fits and the joint-critic
    # extraction still does not, so a post-hoc refit never reruns it
    params.update(methods=[*params["methods"], "mapex_posthoc_td3"])
    save_params(ws / "params.yaml", params, sort_keys=False)
    write_plan(params, ws / "params.yaml", ws)  # `mapex plan`
    assert sorted(i.name for i in stage_items(ws, ["mapex_td3@0"])) == [
        "mapex_td3@0",
        "train_specialist@0",
    ]
    assert sorted(i.name for i in stage_items(ws, ["mapex_posthoc_td3@0"])) == [
        "fit_critics@0-td3-0",
        "fit_critics@0-td3-1",
        "mapex_posthoc_td3@0",
        "train_specialist@0",
    ]
    assert {"critic_fidelity_posthoc@0-td3-0", "evaluate@0-mapex_posthoc_td3"} <= {i.name for i in stage_items(ws)}


def test_a_cell_dvc_cannot_read_is_refused_before_anything_runs(tmp_path, source):
    grid = write_grid(tmp_path / "grid.yaml", {"envs": ["mo-hopper-2obj-v5"], "base": "no_objectives.yaml"})
    result = run_cli(grid, "--remote", tmp_path / "remote", "--repo", source, "--workdir", tmp_path / "work")
    assert result.exit_code == 2
    assert "cell mo-hopper-2obj-v5: DVC cannot read the pipeline" in result.output and "objectives" in result.output


def test_core_install_does_not_need_ray():
    code = (
        "import sys, builtins\n"
        "real = builtins.__import__\n"
        "def block(name, *a, **k):\n"
        "    if name == 'ray' or name.startswith('ray.'):\n"
        "        raise ImportError('no ray')\n"
        "    return real(name, *a, **k)\n"
        "builtins.__import__ = block\n"
        "import pipeline.distributed.driver, pipeline.distributed.errors, stages.repro\n"
        "try:\n"
        "    pipeline.distributed.driver._import_ray()\n"
        "except pipeline.distributed.errors.SweepError as e:\n"
        "    print(e)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert 'pip install -e ".[sweep]"' in r.stdout


# ------------------------------------------------------------------------------------------
# On a two-node Ray cluster

try:
    import ray
except ImportError:  # the optional extra; `make test` installs it
    ray = None


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """Two Ray nodes of one CPU each; the DIES task's worker exits on its first attempt."""
    if ray is None:
        pytest.skip('Ray is the optional extra: pip install -e ".[sweep]" (make test installs it)')
    from ray.cluster_utils import Cluster

    marker = tmp_path_factory.mktemp("fault") / "died"
    os.environ[DIE_ONCE_ENV] = f"{DIES}={marker}"  # inherited by the nodes' workers
    try:
        c = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
        c.add_node(num_cpus=1)
        c.wait_for_nodes()
        ray.init(address=c.address, log_to_driver=False)
    finally:
        del os.environ[DIE_ONCE_ENV]
    yield marker
    ray.shutdown()
    c.shutdown()


@pytest.fixture(scope="module")
def swept(cluster, source, tmp_path_factory):
    """The first sweep of GRID (the whole pipeline of one cell), through the command, and, in
    parallel with it (it uses one core), a plain serial `dvc repro` of the same cell: a fresh
    clone of the commit with the cell's params. Returns (base, result, serial dvc.lock bytes)."""
    base = tmp_path_factory.mktemp("sweep")
    grid = write_grid(base / "grid.yaml", GRID)
    commit = git(source, "rev-parse", "HEAD")
    (cell,) = plan_cells(load_grid(grid), grid, source, commit)
    serial = base / "serial"
    git(base, "clone", "-q", str(source), str(serial))
    checkout_cell(serial, commit, cell.params_text)
    env = {
        **os.environ,
        "PATH": f"{BIN}{os.pathsep}{os.environ['PATH']}",
        "PYTHONPATH": str(serial),
        "MAPEX_TORCH_THREADS": "1",
    }
    log = open(base / "serial.log", "w")
    proc = subprocess.Popen([str(BIN / "dvc"), "repro"], cwd=serial, env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        result = run_cli(
            grid,
            "--remote",
            base / "remote",
            "--repo",
            source,
            "--workdir",
            base / "work",
            "--max-retries",
            2,
            "--scratch",
            base / "scratch",
        )
    finally:
        rc = proc.wait()
        log.close()
    assert rc == 0, (base / "serial.log").read_text()[-3000:]
    return base, result, (serial / "dvc.lock").read_bytes()


MEASURED = ("data/provenance", "data/report")  # outputs holding measured times (core-seconds)


def without_measured(lock: str | dict) -> dict:
    """A dvc.lock's stages (text or its parsed `stages`) with the hashes and sizes of the files under
    MEASURED dropped: those hold what each run cost in seconds, never equal between two runs, while
    every other dependency and output is compared by its hash."""
    stages = yaml.safe_load(lock)["stages"] if isinstance(lock, str) else lock
    out = {}
    for name, stage in stages.items():
        stage = dict(stage)
        for kind in ("deps", "outs"):
            if kind in stage:
                stage[kind] = [{"path": e["path"]} if str(e["path"]).startswith(MEASURED) else e for e in stage[kind]]
        out[name] = stage
    return out


@pytest.mark.slow  # a Ray cluster and whole sweeps: `make test-slow` (CI runs it)
def test_sweep_survives_a_dead_worker_and_writes_the_serial_lock(swept, cluster):
    base, result, serial = swept
    assert result.exit_code == 0, result.output
    assert cluster.exists(), "the fault hook never fired"  # the DIES task's worker did die once
    out = result.output
    assert "ray: 2 CPU, 0 GPU, 2 node(s)" in out
    assert "mo-hopper-2obj-v5 mapex_td3@0: ran" in out  # by its retry
    assert "mo-hopper-2obj-v5: done (11 ran, 0 restored)" in out  # 10 stage items and render
    ws = base / "work" / "mo-hopper-2obj-v5"
    assert (ws / "data" / "report" / "report.md").is_file()
    # the lock equals a plain serial `dvc repro` of the commit with the cell's params, byte for byte
    assert (ws / "params.yaml").read_text() == (base / "serial" / "params.yaml").read_text()
    # every artifact's hash equal; the provenance records and the report carry measured seconds
    # (what each front cost), which no two runs share, so only their paths are compared
    assert without_measured((ws / "dvc.lock").read_text()) == without_measured(serial.decode())
    # every clone is gone, the dead worker's too (its retry removed it)
    assert [p for p in (base / "scratch").rglob("*") if p.is_dir() and p.parent != base / "scratch"] == []


@pytest.mark.slow  # a Ray cluster and whole sweeps: `make test-slow` (CI runs it)
def test_a_second_sweep_runs_nothing(swept, source):
    base, _, _ = swept
    ws = base / "work" / "mo-hopper-2obj-v5"
    lock = (ws / "dvc.lock").read_bytes()
    result = run_cli(base / "grid.yaml", "--remote", base / "remote", "--repo", source, "--workdir", base / "work")
    assert result.exit_code == 0, result.output
    assert "mo-hopper-2obj-v5: up to date" in result.output
    assert "nothing to run" in result.output and ": ran" not in result.output
    assert (ws / "dvc.lock").read_bytes() == lock


@pytest.mark.slow  # a Ray cluster and whole sweeps: `make test-slow` (CI runs it)
def test_a_grid_of_two_envs_shares_and_restores_runs(swept, source, tmp_path):
    """Another grid, up to critic_fidelity@0-td3-0: 2 envs x 2 override sets (`b` changes
    critic_fidelity.episodes). hopper.a has the first sweep's params (another cell name), so its
    tasks restore both items from the run-cache without computing them. Within an env, the two
    sets share one task for the specialists (the same DVC run) and check their critics each."""
    base, _, _ = swept
    grid = {
        "envs": [{"name": "hopper", "id": "mo-hopper-2obj-v5"}, {"name": "cheetah", "id": "mo-halfcheetah-v5"}],
        "seeds": [0],
        "overrides": {"a": {}, "b": {"critic_fidelity": {"episodes": 3}}},
        "targets": ["critic_fidelity@0-td3-0"],
    }
    path = write_grid(tmp_path / "two.yaml", grid)
    result = run_cli(
        path,
        "--remote",
        base / "remote",
        "--repo",
        source,
        "--workdir",
        tmp_path / "work",
        "--scratch",
        base / "scratch",
    )
    assert result.exit_code == 0, result.output
    out = result.output
    assert "hopper.a: done (0 ran, 2 restored)" in out and "hopper.b: done (1 ran, 1 restored)" in out
    assert "cheetah.a: done (2 ran, 0 restored)" in out and "cheetah.b: done (2 ran, 0 restored)" in out
    assert len(re.findall(r"^\[\d+/6\] ", out, re.M)) == 6  # 8 items, 6 tasks
    assert "cheetah.a train_specialist@0 (shared with cheetah.b): ran" in out
    assert "hopper.a train_specialist@0 (shared with hopper.b): restored from the run-cache" in out

    def lock(cell: Path) -> dict:
        return yaml.safe_load((cell / "dvc.lock").read_text())["stages"]

    work, first = tmp_path / "work", lock(base / "work" / "mo-hopper-2obj-v5")
    ha, hb, ca, cb = (
        lock(work / "hopper.a"),
        lock(work / "hopper.b"),
        lock(work / "cheetah.a"),
        lock(work / "cheetah.b"),
    )
    assert all(sorted(x) == sorted(SHARED) for x in (ha, hb, ca, cb))
    assert all(ha[k] == first[k] for k in SHARED)
    for a, b in ((ha, hb), (ca, cb)):
        assert (
            a["train_specialist@0"] == b["train_specialist@0"]
            and a["critic_fidelity@0-td3-0"]["outs"] != b["critic_fidelity@0-td3-0"]["outs"]
        )
    assert ca["train_specialist@0"]["outs"] != ha["train_specialist@0"]["outs"]


SHARED = ("train_specialist@0", "critic_fidelity@0-td3-0")


@pytest.mark.slow  # a Ray cluster and whole sweeps: `make test-slow` (CI runs it)
def test_a_failing_stage_is_reported_not_retried_and_its_downstream_not_run(cluster, source, tmp_path):
    grid = write_grid(
        tmp_path / "bad.yaml",
        {"envs": [{"name": "nope", "id": "mo-nope-v5"}], "seeds": [0], "targets": ["critic_fidelity@0-td3-0"]},
    )
    result = run_cli(
        grid,
        "--remote",
        tmp_path / "remote",
        "--repo",
        source,
        "--workdir",
        tmp_path / "work",
        "--scratch",
        tmp_path / "scratch",
    )
    assert result.exit_code == 1, result.output
    out = result.output
    assert "nope train_specialist@0: FAILED" in out and "mo-nope-v5" in out  # the stage's own error line
    assert "nope critic_fidelity@0-td3-0: not run: upstream train_specialist@0 failed" in out
    assert (
        "stages failed in nope: critic_fidelity@0-td3-0, train_specialist@0 (fix the cause and rerun the sweep" in out
    )
    assert not (tmp_path / "work" / "nope" / "dvc.lock").exists()
    assert list((tmp_path / "scratch" / "nope").iterdir()) == []  # its clone is cleaned up


# ------------------------------------------------------------------------------------------
# An S3 remote: moto's S3 server on 127.0.0.1 (dvc-s3 and moto are test-only installs)


@pytest.fixture
def s3_server():
    pytest.importorskip("dvc_s3", reason="dvc-s3 is a test-only install (make test installs it)")
    moto_server = pytest.importorskip(
        "moto.server", reason="moto[server] is a test-only install (make test installs it)"
    )
    import boto3

    with socket.socket() as sock:  # a free port
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    url = f"http://127.0.0.1:{port}"
    s3 = boto3.client(
        "s3", endpoint_url=url, aws_access_key_id="testing", aws_secret_access_key="testing", region_name="us-east-1"
    )
    s3.create_bucket(Bucket="mapex-sweep")
    yield url, s3
    server.stop()


@pytest.mark.slow  # a Ray cluster and whole sweeps: `make test-slow` (CI runs it)
def test_a_sweep_on_an_s3_remote_matches_the_local_remote(swept, source, tmp_path, s3_server):
    """The first sweep's cell up to critic_fidelity@0-td3-0 again, with an S3-compatible remote: the
    stages compute (the bucket's run-cache is empty), their lock entries equal the local-remote
    sweep's, outputs and run-cache land in the bucket, and a second run restores everything."""
    base, _, _ = swept
    url, s3 = s3_server
    grid = write_grid(tmp_path / "s3.yaml", {**GRID, "targets": ["critic_fidelity@0-td3-0"]})
    args = [
        grid,
        "--remote",
        "s3://mapex-sweep/remote",
        "--repo",
        source,
        "--workdir",
        tmp_path / "work",
        "--scratch",
        tmp_path / "scratch",
        "--remote-option",
        f"endpointurl={url}",
        "--remote-option",
        "access_key_id=testing",
        "--remote-option",
        "secret_access_key=testing",
    ]
    result = run_cli(*args)
    assert result.exit_code == 0, result.output
    assert "mo-hopper-2obj-v5: done (2 ran, 0 restored)" in result.output
    lock = yaml.safe_load((tmp_path / "work" / "mo-hopper-2obj-v5" / "dvc.lock").read_text())["stages"]
    local = yaml.safe_load((base / "work" / "mo-hopper-2obj-v5" / "dvc.lock").read_text())["stages"]
    lock, local = without_measured(lock), without_measured(local)
    assert sorted(lock) == sorted(SHARED) and all(lock[k] == local[k] for k in SHARED)
    keys = [
        o["Key"]
        for page in s3.get_paginator("list_objects_v2").paginate(Bucket="mapex-sweep")
        for o in page.get("Contents", [])
    ]
    assert any(k.startswith("remote/files/md5/") for k in keys) and any(k.startswith("remote/runs/") for k in keys)
    assert (
        "endpointurl"
        not in subprocess.run(["git", "show", "HEAD:.dvc/config"], cwd=source, capture_output=True, text=True).stdout
    )
    again = run_cli(*args)
    assert again.exit_code == 0 and "mo-hopper-2obj-v5: up to date" in again.output
    bad = run_cli(*args[:-6], "--remote-option", "endpointurl")
    assert bad.exit_code == 2 and "expected KEY=VALUE" in bad.output


def test_resume_root_gives_each_task_its_own_shared_progress_dir(tmp_path):
    task = StageTask("hopper.a", "mapex_td3@0", "src", "c0ffee", "", "remote", (), 1, 0.0, None, (), str(tmp_path))
    assert task_resume_dir(task) == tmp_path / "hopper.a" / "mapex_td3_0"
    other = StageTask("hopper.b", "mapex_td3@0", "src", "c0ffee", "", "remote", (), 1, 0.0, None, (), str(tmp_path))
    assert task_resume_dir(other) != task_resume_dir(task)  # cells never share progress
    assert task_resume_dir(StageTask("c", "i", "s", "c", "", "r", (), 1, 0.0)) is None  # default: in the clone


def test_stages_with_worker_processes_reserve_a_cpu_per_process():
    """train_specialist.processes: 2 (the quickstart's params) makes a train_specialist task ask
    Ray for 2 CPUs with 1 torch thread per process, unless the grid says otherwise; stages
    without workers keep the defaults."""
    params = {"train_specialist": {"processes": 2}, "train_pderl": {}}
    assert stage_processes(params, "train_specialist") == 2
    assert stage_processes(params, "train_pderl") == 1
    assert stage_processes(params, "extract") == 1
    grid = Grid(envs=["mo-hopper-2obj-v5"])
    assert _resources(grid, "train_specialist", 0, 2) == (2.0, 0.0, 1)
    assert _resources(grid, "extract", 0, 1) == (1.0, 0.0, 1)
    given = Grid(envs=["mo-hopper-2obj-v5"], resources={"train_specialist": {"cpus": 4}})
    assert _resources(given, "train_specialist", 0, 2) == (4.0, 0.0, 2)  # 2 processes x 2 threads
    assert _resources(given, "train_specialist", 1, 1, True)[1:] == (1.0, 4)  # a GPU, 1 process x 4 threads


def test_an_upstream_output_missing_after_the_pull_is_named(tmp_path, monkeypatch):
    """The task pulls its upstream items' outputs with one `dvc pull dvc.yaml` (a path target each
    made DVC re-parse dvc.yaml and dvc.lock per path); whatever did not arrive fails the task by name."""
    import pipeline.distributed.task as task_mod

    calls = []
    monkeypatch.setattr(task_mod, "_run_dvc", lambda cwd, env, *args: calls.append(args) or "")
    (tmp_path / "data" / "score").mkdir(parents=True)
    (tmp_path / "data" / "score" / "metrics.json").write_text("{}")
    task = StageTask("c", "report", "s", "c", "", "/remote", ("data/score/metrics.json",), 1, 0.0)
    task_mod._pull_upstream(tmp_path, {}, task)  # everything there: no error
    assert calls == [("pull", "--quiet", "--allow-missing", "dvc.yaml")]
    lost = StageTask("c", "report", "s", "c", "", "/remote", ("data/score/metrics.json", "data/evaluate/x.csv"), 1, 0.0)
    with pytest.raises(
        RuntimeError, match=r"1 upstream output\(s\) not in the remote /remote after `dvc pull`: data/evaluate/x.csv$"
    ):
        task_mod._pull_upstream(tmp_path, {}, lost)


def test_data_added_with_dvc_add_is_pulled_by_the_task_that_reads_it(tmp_path):
    """An input the user tracked with `dvc add` and pushed (an imported specialist's model file) is
    no stage item; the item that reads it pulls its .dvc file in its clone, and its hash is part
    of the item's signature (a sweep of a mixed-sources preset failed on it before)."""
    from pipeline.distributed.task import run_stage_task

    repo, remote = tmp_path / "repo", tmp_path / "remote"
    repo.mkdir()
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ['PATH']}"}

    def sh(*args: str) -> None:
        subprocess.run(args, cwd=repo, env=env, check=True, capture_output=True)

    sh("git", "init", "-q")
    sh("git", "config", "user.email", "t@example.com")
    sh("git", "config", "user.name", "t")
    sh(str(BIN / "dvc"), "init", "-q")
    (repo / "models").mkdir()
    (repo / "models" / "speed.bin").write_bytes(b"weights v1")
    sh(str(BIN / "dvc"), "add", "-q", "models/speed.bin")
    (repo / "dvc.yaml").write_text(
        "stages:\n"
        "  use:\n    cmd: cp models/speed.bin copy.bin\n    deps: [models/speed.bin]\n    outs: [copy.bin]\n"
        "  after:\n    cmd: cp copy.bin after.bin\n    deps: [copy.bin]\n    outs: [after.bin]\n"
    )
    (repo / "params.yaml").write_text("{}\n")
    sh("git", "add", "-A")
    sh("git", "commit", "-qm", "toy")
    (repo / ".dvc" / "config.local").write_text(f"['remote \"r\"']\n    url = {remote}\n")
    sh(str(BIN / "dvc"), "push", "-q", "-r", "r", "models/speed.bin.dvc")

    items = {i.name: i for i in stage_items(repo)}
    assert list(items) == ["use", "after"]  # the .dvc file is data, not an item
    assert items["use"].sources == ("models/speed.bin.dvc",) and items["use"].pull == ("models/speed.bin",)
    assert items["after"].sources == () and items["after"].upstream == ("use",)
    assert [i.name for i in stage_items(repo, ["use"])] == ["use"]

    # the task clones the commit (no model file in it), pulls the model and runs the stage
    commit = git(repo, "rev-parse", "HEAD")
    it = items["use"]
    task = StageTask(
        "c",
        "use",
        str(repo),
        commit,
        "{}\n",
        str(remote),
        it.pull,
        1,
        0.0,
        str(tmp_path / "scratch"),
        (),
        None,
        it.sources,
    )
    result = run_stage_task(task)
    assert result.executed and result.lock["outs"][0]["path"] == "copy.bin"
    assert (
        result.lock["deps"][0]["md5"]
        == yaml.safe_load((repo / "models" / "speed.bin.dvc").read_text())["outs"][0]["md5"]
    )

    # another model: another signature for its reader and everything downstream
    (repo / "models" / "speed.bin").write_bytes(b"weights v2")
    sh(str(BIN / "dvc"), "add", "-q", "models/speed.bin")
    again = {i.name: i for i in stage_items(repo)}
    assert all(again[n].signature != items[n].signature for n in ("use", "after"))


def _without_devices(params: dict) -> dict:
    """`params` with every section's `device` key removed: each stage at its model's default."""
    return {
        k: ({kk: vv for kk, vv in v.items() if kk != "device"} if isinstance(v, dict) else v) for k, v in params.items()
    }


def test_every_stage_that_trains_or_extracts_is_planned_with_a_gpu(tmp_path):
    """On a (simulated) cluster with a GPU, `gpus: auto` gives one to every stage item that
    trains or extracts, the variant stages and the baselines included, read from the params each
    item lists; evaluation (device: cpu by default), scoring, the fidelity checks, interpolation
    and the report get none; a variant that sets its device to cpu gets none either."""
    from support.dvc_repo import make_repo
    from support.tiny_params import TINY_ALL, with_lists

    methods = [*TINY_ALL["methods"], "interpolate_td3", "hybrid", "warm", "interp_shared", "hybrid_cpu"]
    variants = {
        "hybrid": {"of": "mapex_td3", "extract": {"init": "interpolate"}},
        "warm": {"of": "warmup_only_td3", "extract": {"warmup_steps": 10}},
        "td3_shared": {"of": "td3", "td3": {"shared_init": True}},
        "interp_shared": {"of": "interpolate_td3", "specialists": "td3_shared"},
        "hybrid_cpu": {"of": "mapex_td3", "specialists": "td3_shared", "extract": {"device": "cpu"}},
    }
    params = with_lists(_without_devices({**TINY_ALL, "methods": methods, "variants": variants}))
    root = make_repo(tmp_path / "repo", params)
    grid = Grid(envs=["mo-hopper-2obj-v5"])
    gpus = {}
    for it in stage_items(root):
        gpus[it.name] = _resources(grid, it.stage, 1.0, 1, it.on_device)[1]
        assert _resources(grid, it.stage, 0.0, 1, it.on_device)[1] == 0.0  # no GPU in the cluster: none
    by_stage: dict[str, set[float]] = {}
    for name, g in gpus.items():
        by_stage.setdefault(name.split("@")[0], set()).add(g)
    # every method has a stage of its own: the variant told device: cpu gets no GPU, its base does
    assert by_stage["hybrid_cpu"] == {0.0} and by_stage["hybrid"] == {1.0}
    trains = {
        "train_specialist",
        "train_specialist_variant",
        "train_pderl",
        "fit_critics",
        "mapex_td3",
        "warmup_only_td3",
        "mapex_pderl",
        "mapex_posthoc_td3",
        "hybrid",
        "warm",
        "mopderl",
        "morld",
    }
    assert trains <= set(by_stage), sorted(set(trains) - set(by_stage))
    for stage in trains:
        assert by_stage[stage] == {1.0}, (stage, by_stage[stage])
    for stage in ("evaluate", "score", "critic_fidelity", "interpolate_td3", "interp_shared", "report"):
        assert by_stage[stage] == {0.0}, (stage, by_stage[stage])
