"""Sweeps beyond one machine: the DVC pipeline's stage items as Ray tasks, a shared DVC remote
as the artifact store (issue 12; user guide: docs/sweeps.md).

How a grid maps onto DVC
------------------------
A grid file lists envs, seeds and named param override sets. One *cell* is one (env, override
set): its params.yaml is the base params (or the env's preset) with the env's and the override
set's values merged in and the grid's seeds. dvc.yaml already fans a params.yaml out over seeds,
objectives and variants, so a cell is one ordinary DVC workspace (a clone of the project's HEAD
commit with the cell's params.yaml, dvc.lock removed) and its stage items (`train_specialist@0`,
`extract@0-td3-mapex`, ..., `report`) are exactly what `dvc repro` would run there.

Tasks: one Ray task per stage item, from DVC's own DAG (`Repo.index.graph` of the cell
workspace). A task's arguments are the results of its direct upstream tasks, so Ray runs it only
after them; a result carries the upstream item's dvc.lock entry. The task clones the commit into
a scratch directory, writes the cell's params.yaml and the upstream entries into the clone's
dvc.lock, runs `dvc repro --single-item --pull <item>` (a missing input is pulled from the
remote; the stage is restored from the remote's run-cache if this exact run was published
before, else computed), publishes outputs and run-cache entry with `dvc push --run-cache <item>`
and deletes the clone. Workers never write the driver's files.

Items shared between cells: two cells whose item has the same command, the same values of the
params it declares in dvc.yaml and the same upstream (e.g. the specialists of two override sets
that change only `extract`) are one computation for DVC (one run-cache key). The driver submits
it once and hands its result to both cells, so the remote never holds two different runs under
one key (which would make the lock's restore ambiguous).

The lock: when every task of a cell succeeded, the driver runs `dvc repro --pull` once in the
cell's workspace. Every stage is restored from the remote's run-cache; `mapex` is shadowed by
a stub that fails, so nothing can be recomputed there. The resulting dvc.lock is the one a serial
`dvc repro` of the cell writes (tested byte for byte).

Dead workers: Ray retries a task whose worker process or node died (`max_retries`); a stage that
exits with an error raises `StageFailed`, which is not retried (`retry_exceptions=False`). A
retry starts from a fresh clone and redoes only its own stage: upstream outputs come from the
remote. A second sweep with nothing changed runs no stage: a cell whose workspace is at the
commit with its params and a dvc.lock that `dvc status` finds up to date submits no task, and a
task whose run is in the remote's run-cache restores instead of computing.

Provenance: artifacts record the commit with `git_dirty: true`, as for any run whose
params.yaml differs from the commit's; the code is exactly the commit (the driver refuses to
start from uncommitted code changes).

Ray is optional (`pip install -e .[sweep]`) and imported only by the driver functions.
"""

from __future__ import annotations

import copy
import hashlib
import json
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from pipeline.params import KNOWN_SECTIONS, ParamsError
from pipeline.core.resume import RESUME_ROOT_ENV

# Stages that get a GPU when the cluster has one (resources gpus: auto); the others run on CPU.
GPU_STAGES = ("train_specialist", "train_pderl", "fit_critics", "extract", "extract_posthoc")
SWEEP_EXTRA = 'pip install -e ".[sweep]"'
# Test hook: "<cell>/<item>=<marker file>" makes that task's worker die (os._exit) once, after its
# stage ran and before it published anything, the worst moment for a worker to die.
DIE_ONCE_ENV = "MAPEX_SWEEP_TEST_DIE_ONCE"
CELL_KEY = "mapex.sweepcell"  # git config key marking a directory as a sweep cell workspace
NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


class GridError(ParamsError):
    """The grid file is missing, unreadable or invalid; the message names the file and the key."""


class SweepError(RuntimeError):
    """A sweep cannot start or did not complete; `exit_code` 2 for bad input, 1 for failed stages."""

    def __init__(self, message: str, exit_code: int = 2):
        super().__init__(message)
        self.exit_code = exit_code


class StageFailed(RuntimeError):
    """A stage item's command failed on a worker (not retried: the same input fails again)."""

    def __init__(self, cell: str, item: str, message: str):
        super().__init__(f"{cell}: {item}: {message}")
        self.cell, self.item, self.detail = cell, item, message

    def __reduce__(self):  # pickled across Ray processes with its fields
        return (StageFailed, (self.cell, self.item, self.detail))


# ----------------------------------------------------------------------------------------------
# The grid file


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class EnvSpec(_Strict):
    """One env of the grid. `id` alone takes the base params with env.id (and the env's
    reference point from presets/reference_points.yaml); `preset` starts from that params file
    instead of the base; `params` is merged in on top of either."""

    name: str | None = Field(None, description="cell name prefix (default: the env id)")
    id: str | None = Field(None, description="MO-Gymnasium env id, set as env.id on the base params")
    preset: str | None = Field(None, description="params file (repository path) replacing the base, e.g. presets/paper/mo-hopper-2obj-v5.yaml")
    params: dict[str, Any] = Field(default_factory=dict, description="params merged in, section by section")

    @field_validator("name")
    @classmethod
    def _name(cls, v: str | None) -> str | None:
        if v is not None and not NAME.match(v):
            raise ValueError(f"{v!r}: use letters, digits, '.', '_' and '-' (it names a directory)")
        return v


class ResourceSpec(_Strict):
    """What one task of a stage asks Ray for."""

    cpus: float = Field(1.0, gt=0, description="CPUs reserved per task")
    gpus: float | Literal["auto"] = Field(
        "auto", description="GPUs per task (fractions share one GPU); auto: 1 for the training stages when the cluster has a GPU, else 0"
    )
    threads: int | None = Field(
        None, ge=1, description="MAPEX_TORCH_THREADS for the stage (default: cpus, at least 1; shared among a stage's processes)"
    )

    @field_validator("gpus")
    @classmethod
    def _gpus(cls, v: float | str) -> float | str:
        if not isinstance(v, str) and v < 0:
            raise ValueError("must be >= 0 or 'auto'")
        return v


class Grid(_Strict):
    base: str = Field("params.yaml", description="params file (repository path, read at the commit) each env starts from")
    envs: list[EnvSpec] = Field(min_length=1, description="env ids, preset paths (*.yaml) or mappings")
    seeds: list[int] | None = Field(None, min_length=1, description="the seeds of every cell (default: the params' own)")
    overrides: dict[str, dict[str, Any]] | None = Field(
        None, description="named param override sets; each env runs once per set (default: one cell per env)"
    )
    resources: dict[str, ResourceSpec] = Field(default_factory=dict, description="per dvc.yaml stage name")
    targets: list[str] | None = Field(
        None, min_length=1, description="dvc.yaml stages or stage items to reproduce, with their upstream (default: all)"
    )

    @field_validator("envs", mode="before")
    @classmethod
    def _env_shorthands(cls, v: Any) -> Any:
        if not isinstance(v, list):
            return v
        return [({"preset": e} if e.endswith((".yaml", ".yml")) else {"id": e}) if isinstance(e, str) else e for e in v]

    @field_validator("seeds")
    @classmethod
    def _seeds(cls, v: list[int] | None) -> list[int] | None:
        if v is not None and (len(set(v)) != len(v) or any(s < 0 for s in v)):
            raise ValueError(f"seeds must be unique and >= 0, got {v}")
        return v

    @field_validator("overrides")
    @classmethod
    def _override_names(cls, v: dict[str, Any] | None) -> dict[str, Any] | None:
        for name in v or {}:
            if not NAME.match(str(name)):
                raise ValueError(f"override set name {name!r}: use letters, digits, '.', '_' and '-'")
        return v


def load_grid(path: Path) -> Grid:
    """Read and validate a grid file; every problem becomes one GridError naming file and key."""
    path = Path(path)
    if not path.is_file():
        raise GridError(f"{path}: grid file not found")
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise GridError(f"{path}: not valid YAML ({exc})") from None
    if not isinstance(raw, dict):
        raise GridError(f"{path}: expected a mapping with keys envs, seeds, overrides, base, resources")
    try:
        return Grid.model_validate(raw)
    except ValidationError as exc:
        lines = []
        for err in exc.errors():
            loc = ".".join(str(p) for p in err["loc"])
            if err["type"] == "extra_forbidden":
                lines.append(f"{loc}: unknown key")
            elif err["type"] == "missing":
                lines.append(f"{loc}: required key is missing")
            else:
                lines.append(f"{loc} = {err.get('input')!r}: {err['msg']}")
        raise GridError(f"{path}: invalid grid:\n  " + "\n  ".join(dict.fromkeys(lines))) from None


def merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """A deep copy of `base` with `over` merged in, mapping by mapping (lists are replaced)."""
    out = copy.deepcopy(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


@dataclass(frozen=True)
class Cell:
    """One grid cell: a name (its workspace directory) and the params.yaml text it runs."""

    name: str
    params: dict[str, Any]
    params_text: str


def _git(cwd: Path | str, *args: str, env: dict[str, str] | None = None, input: str | None = None) -> str:
    r = subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, env=env, input=input)
    if r.returncode != 0:
        raise SweepError(f"git {' '.join(args)} (in {cwd}) failed: {r.stderr.strip() or r.stdout.strip()}")
    return r.stdout


def _yaml_at(repo: Path, commit: str, path: str, where: str) -> dict[str, Any]:
    r = subprocess.run(["git", "show", f"{commit}:{path}"], cwd=repo, capture_output=True, text=True)
    if r.returncode != 0:
        raise GridError(f"{where}: {path} is not in commit {commit[:12]} of {repo} (workers clone that commit)")
    try:
        data = yaml.safe_load(r.stdout)
    except yaml.YAMLError as exc:
        raise GridError(f"{where}: {path} at {commit[:12]} is not valid YAML ({exc})") from None
    if not isinstance(data, dict):
        raise GridError(f"{where}: {path} at {commit[:12]} is not a mapping")
    return data


def validate_params(params: dict[str, Any], where: str) -> None:
    """Check a cell's params with the stages' own pydantic models, before anything runs."""
    from pipeline.params import section
    from pipeline.params.registry import section_models

    unknown = sorted(set(params) - set(KNOWN_SECTIONS))
    if unknown:
        raise GridError(f"{where}: unknown top-level params key(s) {unknown}; expected some of {list(KNOWN_SECTIONS)}")
    models = section_models()
    for name, model in models.items():
        try:
            section(params, name, model, where)
        except ParamsError as exc:
            raise GridError(str(exc)) from None


def plan_cells(grid: Grid, grid_path: Path, repo: Path, commit: str) -> list[Cell]:
    """The grid's cells in order (envs outer, override sets inner), params validated."""
    base = _yaml_at(repo, commit, grid.base, f"{grid_path}: base")
    refs_raw = subprocess.run(
        ["git", "show", f"{commit}:presets/reference_points.yaml"], cwd=repo, capture_output=True, text=True
    )
    ref_points = (yaml.safe_load(refs_raw.stdout) or {}) if refs_raw.returncode == 0 else {}
    overrides = grid.overrides if grid.overrides is not None else {"": {}}
    cells: list[Cell] = []
    for i, entry in enumerate(grid.envs):
        where = f"{grid_path}: envs.{i}"
        if entry.preset is not None and entry.id is not None:
            raise GridError(f"{where}: give either id or preset, not both (a preset names its env)")
        if entry.preset is not None:
            params = _yaml_at(repo, commit, entry.preset, f"{where}.preset")
            default_name = str((params.get("env") or {}).get("id") or Path(entry.preset).stem)
        else:
            params = copy.deepcopy(base)
            if entry.id is not None:
                env = dict(params.get("env") or {})
                if env.get("id") != entry.id:
                    env["id"] = entry.id
                    if entry.id in ref_points:
                        env["reference_point"] = ref_points[entry.id]
                    else:
                        env.pop("reference_point", None)
                params["env"] = env
            default_name = str((params.get("env") or {}).get("id") or "env")
        params = merge(params, entry.params)
        env_name = entry.name or default_name
        if not NAME.match(env_name):
            raise GridError(f"{where}: cell name {env_name!r} is not a valid directory name; give the env a name")
        for set_name, over in overrides.items():
            cell_params = merge(params, over or {})
            if grid.seeds is not None:
                cell_params["seeds"] = list(grid.seeds)
                for key in ("pderl_seeds", "mopderl_seeds", "morld_seeds"):  # [] or every seed (RunParams)
                    if cell_params.get(key):
                        cell_params[key] = list(grid.seeds)
            name = f"{env_name}.{set_name}" if set_name else env_name
            validate_params(cell_params, f"{grid_path}: cell {name}")
            # No cell or grid name in the text, so that cells of equal params are equal checkouts.
            text = "# params of a `mapex sweep` grid cell (docs/sweeps.md)\n" + yaml.safe_dump(cell_params, sort_keys=False)
            cells.append(Cell(name, cell_params, text))
    names = [c.name for c in cells]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise GridError(f"{grid_path}: cells {dupes} appear more than once; give the envs distinct names")
    return cells


# ----------------------------------------------------------------------------------------------
# Workspaces


def checkout_cell(clone: Path, commit: str, params_text: str) -> None:
    """Make `clone` the cell's checkout: `commit` (detached), the cell's params.yaml, no dvc.lock."""
    _git(clone, "checkout", "--quiet", "--force", "--detach", commit)
    (clone / "params.yaml").write_text(params_text)
    (clone / "dvc.lock").unlink(missing_ok=True)


def _has_commit(clone: Path, commit: str) -> bool:
    return subprocess.run(["git", "cat-file", "-e", f"{commit}^{{commit}}"], cwd=clone, capture_output=True).returncode == 0


def _fetch_commit(clone: Path, source: str, commit: str) -> None:
    """Make `commit` available in `clone`: fetched from `source` by name if no branch has it."""
    if not _has_commit(clone, commit):
        _git(clone, "fetch", "--quiet", source)
    if not _has_commit(clone, commit):
        _git(clone, "fetch", "--quiet", source, commit)


def _clone_at(source: str, commit: str, dest: Path) -> None:
    """`git clone` source into dest, with `commit` available there."""
    _git(dest.parent, "clone", "--quiet", "--no-checkout", source, str(dest))
    _fetch_commit(dest, source, commit)


def configure_remote(workspace: Path, remote: str, options: tuple[tuple[str, str], ...] = ()) -> None:
    """Point the workspace's DVC at the shared remote (.dvc/config.local, which git ignores), with
    the remote's extra settings (e.g. endpointurl, access_key_id for an S3-compatible server)."""
    extra = "".join(f"    {k} = {v}\n" for k, v in options)
    (workspace / ".dvc" / "config.local").write_text(
        f"[core]\n    remote = mapex-sweep\n['remote \"mapex-sweep\"']\n    url = {remote}\n{extra}"
    )


def _dvc_bin() -> str:
    here = Path(sys.executable).with_name("dvc")
    return str(here) if here.is_file() else "dvc"


def _run_dvc(cwd: Path, env: dict[str, str], *args: str) -> str:
    r = subprocess.run([_dvc_bin(), *args], cwd=cwd, env=env, capture_output=True, text=True)
    out = r.stdout + r.stderr
    if r.returncode != 0:
        tail = "\n".join(out.strip().splitlines()[-40:])
        raise RuntimeError(f"dvc {' '.join(args)} exited with {r.returncode}:\n{tail}")
    return out


@dataclass(frozen=True)
class StageItem:
    """One stage item of a cell's DAG, as DVC sees it."""

    name: str  # dvc addressing, e.g. extract@0-td3-mapex
    stage: str  # dvc.yaml stage name, e.g. extract
    upstream: tuple[str, ...]  # direct upstream items
    pull: tuple[str, ...]  # upstream outputs inside a folder dep (pulled before `dvc repro --pull`)
    signature: str  # what DVC's run-cache key depends on besides code: cmd, declared params, upstream


def stage_items(workspace: Path, targets: list[str] | None = None) -> list[StageItem]:
    """The cell's stage items in a topological order, from DVC's own index (dvc.yaml + params):
    all of them, or `targets` (stage names or items, as `dvc repro` takes them) and their upstream."""
    import networkx as nx
    from dvc.dependency.param import ParamsDependency
    from dvc.repo import Repo

    items = []
    signatures: dict[str, str] = {}
    with Repo(str(workspace)) as repo:
        graph = repo.index.graph  # edges point from a stage to the stages it depends on
        root = repo.root_dir
        if targets:
            keep = set()
            for t in targets:
                hits = [s for s in graph if s.name == t or s.name.split("@")[0] == t]
                if not hits:
                    raise ValueError(f"target {t!r} is no stage or stage item of dvc.yaml (have {sorted({s.name.split('@')[0] for s in graph})})")
                for s in hits:
                    keep |= {s} | nx.descendants(graph, s)
            graph = graph.subgraph(keep)
        # Ray starts ready tasks roughly in submission order: the longest chain of dependents first
        # (the critical path: training before the fidelity checks that nothing waits for).
        height: dict[Any, int] = {}
        for stage in nx.topological_sort(graph):  # dependents before their upstream
            height[stage] = 1 + max((height[d] for d in graph.predecessors(stage)), default=0)
        for stage in nx.lexicographical_topological_sort(graph.reverse(copy=False), key=lambda s: (-height[s], s.name)):
            ups = sorted(graph.successors(stage), key=lambda s: s.name)
            # `dvc repro --pull` pulls a missing dep that is an upstream output (or inside one)
            # itself; a dep that is a folder holding outputs (report's data/evaluate) it cannot,
            # so the task pulls those outputs first.
            pull = set()
            for dep in stage.deps:
                for up in ups:
                    for out in up.outs:
                        if out.fs_path != dep.fs_path and out.fs.isin(out.fs_path, dep.fs_path):
                            pull.add(os.path.relpath(out.fs_path, root))
            params = {
                os.path.relpath(d.fs_path, root): d.read_params() for d in stage.deps if isinstance(d, ParamsDependency)
            }
            key = json.dumps(
                {"item": stage.name, "cmd": stage.cmd, "params": params, "upstream": [signatures[u.name] for u in ups]},
                sort_keys=True, default=str,
            )
            signatures[stage.name] = hashlib.sha256(key.encode()).hexdigest()
            items.append(StageItem(
                stage.name, stage.name.split("@")[0], tuple(u.name for u in ups), tuple(sorted(pull)), signatures[stage.name],
            ))
    return items


# ----------------------------------------------------------------------------------------------
# The task (runs on a Ray worker; plain Python, so it is testable without Ray)


@dataclass(frozen=True)
class StageTask:
    cell: str
    item: str
    source: str  # git URL or path the worker clones
    commit: str  # code commit
    params_text: str  # the cell's params.yaml
    remote: str
    pull: tuple[str, ...]
    threads: int
    gpus: float
    scratch: str | None = None
    remote_options: tuple[tuple[str, str], ...] = ()  # DVC remote settings besides its url
    resume_root: str | None = None  # shared storage for the stages' resume progress (MAPEX_RESUME_ROOT)


@dataclass(frozen=True)
class StageResult:
    cell: str
    item: str
    lock: dict[str, Any]  # the item's dvc.lock entry
    executed: bool  # the stage's command ran (False: restored from the run-cache)
    seconds: float
    host: str
    phases: dict[str, float] = field(default_factory=dict)  # seconds: clone, pull, repro, push


def _safe(item: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]", "_", item)


def _remove_dead_clones(root: Path, item: str, host: str) -> None:
    """Delete clones of this item left on this host by workers that died (their pid is gone)."""
    if not root.is_dir():
        return
    prefix = f"{_safe(item)}.{host}."
    for d in root.iterdir():
        if d.name.startswith(prefix) and d.name[len(prefix):].isdigit():
            try:
                os.kill(int(d.name[len(prefix):]), 0)
            except ProcessLookupError:
                shutil.rmtree(d, ignore_errors=True)
            except PermissionError:
                pass


def _normalised(entry: dict[str, Any]) -> dict[str, Any]:
    out = dict(entry)
    for key in ("deps", "outs"):
        if isinstance(out.get(key), list):
            out[key] = sorted(out[key], key=lambda d: str(d.get("path")))
    return out


def _keep_own_run(clone: Path, lock: dict[str, Any]) -> int:
    """Delete the run-cache entries the clone pulled, keeping this stage's (so the push uploads
    one entry, not the whole grid's). Returns how many entries match this stage's lock entry."""
    runs = clone / ".dvc" / "cache" / "runs"
    own = _normalised(lock)
    kept = 0
    for f in runs.glob("*/*/*") if runs.is_dir() else []:
        try:
            same = _normalised(yaml.safe_load(f.read_text()) or {}) == own
        except (OSError, yaml.YAMLError):
            same = False
        if same:
            kept += 1
        else:
            f.unlink()
    return kept


def _maybe_die(task: StageTask) -> None:
    spec = os.environ.get(DIE_ONCE_ENV, "")
    target, _, marker = spec.partition("=")
    if target == f"{task.cell}/{task.item}" and marker:
        try:
            fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            return
        os.close(fd)
        os._exit(1)


def stage_env(clone: Path, threads: int, gpus: float) -> dict[str, str]:
    """The environment a stage runs in: this interpreter's bin first, the clone's code on
    PYTHONPATH, the thread count, and no GPU unless the task holds one."""
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(clone), env.get("PYTHONPATH", "")) if p)
    for var in ("MAPEX_TORCH_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        env[var] = str(threads)
    if gpus == 0:
        env["CUDA_VISIBLE_DEVICES"] = ""
    return env


def task_resume_dir(task: StageTask) -> Path | None:
    """The task's own directory under --resume-root (None without one): long stages (specialist
    and PDERL training, extraction, the baselines) checkpoint there instead of in the worker's
    clone, so the retry of a task whose node died resumes instead of starting over."""
    if not task.resume_root:
        return None
    return Path(task.resume_root) / _safe(task.cell) / _safe(task.item)


def run_stage_task(task: StageTask, *upstream: StageResult) -> StageResult:
    """Run one stage item in a fresh clone: the Ray task body. Upstream results are its args."""
    start = time.monotonic()
    phases: dict[str, float] = {}
    host = socket.gethostname()
    root = Path(task.scratch or Path(tempfile.gettempdir()) / "mapex-sweep") / task.cell
    root.mkdir(parents=True, exist_ok=True)
    _remove_dead_clones(root, task.item, host)
    clone = root / f"{_safe(task.item)}.{host}.{os.getpid()}"
    shutil.rmtree(clone, ignore_errors=True)
    try:
        try:
            _clone_at(task.source, task.commit, clone)
            checkout_cell(clone, task.commit, task.params_text)
        except SweepError as exc:
            raise StageFailed(task.cell, task.item, str(exc)) from None
        phases["clone"] = time.monotonic() - start
        configure_remote(clone, task.remote, task.remote_options)
        if upstream:
            lock = {"schema": "2.0", "stages": {u.item: u.lock for u in upstream}}
            (clone / "dvc.lock").write_text(yaml.safe_dump(lock, sort_keys=False))
        env = stage_env(clone, task.threads, task.gpus)
        progress = task_resume_dir(task)
        if progress is not None:  # a retry, on any node, resumes the stage from here
            env[RESUME_ROOT_ENV] = str(progress)
        try:
            t = time.monotonic()
            if task.pull:
                _run_dvc(clone, env, "pull", "--quiet", *task.pull)
                phases["pull"] = time.monotonic() - t
            t = time.monotonic()
            out = _run_dvc(clone, env, "repro", "--single-item", "--pull", task.item)
            phases["repro"] = time.monotonic() - t
        except RuntimeError as exc:
            raise StageFailed(task.cell, task.item, str(exc)) from None
        executed = f"Running stage '{task.item}'" in out
        _maybe_die(task)
        entry = (yaml.safe_load((clone / "dvc.lock").read_text()) or {}).get("stages", {}).get(task.item)
        if not entry:
            raise StageFailed(task.cell, task.item, "dvc repro wrote no dvc.lock entry for it")
        if _keep_own_run(clone, entry) == 0:
            raise StageFailed(task.cell, task.item, "no run-cache entry matches its dvc.lock entry (is every out cached?)")
        try:
            t = time.monotonic()
            _run_dvc(clone, env, "push", "--quiet", "--run-cache", task.item)
            phases["push"] = time.monotonic() - t
        except RuntimeError as exc:
            raise StageFailed(task.cell, task.item, str(exc)) from None
        if progress is not None:  # published: its progress is of no more use
            shutil.rmtree(progress, ignore_errors=True)
        return StageResult(task.cell, task.item, entry, executed, time.monotonic() - start, host, phases)
    finally:
        shutil.rmtree(clone, ignore_errors=True)


# ----------------------------------------------------------------------------------------------
# The driver


@dataclass
class CellResult:
    name: str
    workspace: Path
    status: str = "pending"  # up to date | done | failed | planned
    executed: list[str] = field(default_factory=list)  # stage items computed by this sweep
    restored: list[str] = field(default_factory=list)  # stage items restored from the run-cache
    failed: dict[str, str] = field(default_factory=dict)  # item -> error


@dataclass
class CellPlan:
    cell: Cell
    workspace: Path
    up_to_date: bool
    items: list[StageItem] = field(default_factory=list)


def _repo_root(path: Path) -> Path:
    return Path(_git(path, "rev-parse", "--show-toplevel").strip())


def _check_clean(repo: Path, commit: str) -> None:
    dirty = [line for line in _git(repo, "status", "--porcelain", "--untracked-files=no", "--", ".", ":!dvc.lock").splitlines() if line]
    if dirty:
        files = ", ".join(line[3:] for line in dirty[:10]) + (", ..." if len(dirty) > 10 else "")
        raise SweepError(
            f"{repo} has uncommitted changes ({files}); workers run commit {commit[:12]}, so commit them first"
        )


def prepare_workspace(ws: Path, cell: Cell, source: str, commit: str, targets: list[str] | None = None) -> bool:
    """Make `ws` the cell's checkout (see checkout_cell); return whether it is up to date.

    Up to date: it already was that checkout, with a dvc.lock that matches its files (`dvc
    status` clean), i.e. an earlier sweep completed this cell. A workspace that changes commit
    or params loses its outputs and dvc.lock (untracked files), keeping its DVC cache.
    """
    if ws.exists():
        if _git_config(ws, CELL_KEY) != cell.name:
            raise SweepError(f"{ws} exists and is not the sweep workspace of cell {cell.name}; move it or pick another --workdir")
        _fetch_commit(ws, source, commit)
    else:
        ws.parent.mkdir(parents=True, exist_ok=True)
        _clone_at(source, commit, ws)
        _git(ws, "config", CELL_KEY, cell.name)
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ws, capture_output=True, text=True).stdout.strip()
    params = ws / "params.yaml"
    if (
        head == commit and params.is_file() and params.read_text() == cell.params_text
        and (ws / "dvc.lock").is_file() and _dvc_status_clean(ws, targets)
    ):
        return True
    _git(ws, "checkout", "--quiet", "--force", "--detach", commit)
    _git(ws, "clean", "-ffdxq", "-e", "/.dvc/cache/", "-e", "/.dvc/tmp/")
    checkout_cell(ws, commit, cell.params_text)
    return False


def _git_config(ws: Path, key: str) -> str | None:
    r = subprocess.run(["git", "config", "--get", key], cwd=ws, capture_output=True, text=True)
    return r.stdout.strip() if r.returncode == 0 else None


def _dvc_status_clean(ws: Path, targets: list[str] | None = None) -> bool:
    from dvc.repo import Repo

    try:
        with Repo(str(ws)) as repo:
            # targets as path:name, since DVC resolves a bare name against the working directory
            full = [f"{Path(repo.root_dir) / 'dvc.yaml'}:{t}" for t in targets] if targets else None
            return not repo.status(targets=full, with_deps=True)
    except Exception:  # noqa: BLE001 - a workspace DVC cannot read is simply not up to date
        return False


def write_lock(ws: Path, remote: str, targets: list[str] | None = None, remote_options: tuple[tuple[str, str], ...] = ()) -> str:
    """`dvc repro --pull` in the cell workspace: every stage restored from the remote's run-cache,
    dvc.lock written once. `mapex` is shadowed by a failing stub, so nothing is recomputed here."""
    configure_remote(ws, remote, remote_options)
    (ws / "dvc.lock").unlink(missing_ok=True)
    stub_dir = Path(tempfile.mkdtemp(prefix="mapex-sweep-stub-"))
    try:
        stub = stub_dir / "mapex"
        stub.write_text(
            "#!/bin/sh\necho \"mapex sweep: this stage's run is not in the remote's run-cache; "
            "the driver does not compute stages (rerun the sweep)\" >&2\nexit 3\n"
        )
        stub.chmod(0o755)
        env = dict(os.environ)
        env["PATH"] = f"{stub_dir}{os.pathsep}{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
        # With targets, DVC orders a small subgraph by iterating a set of stages, i.e. by Python's
        # per-process string hashes; a fixed seed makes the lock's stage order repeatable (a
        # serial `PYTHONHASHSEED=0 dvc repro <targets>` writes the same bytes). Without targets
        # the order is dvc.yaml's and the seed changes nothing.
        env["PYTHONHASHSEED"] = "0"
        return _run_dvc(ws, env, "repro", "--pull", *(targets or []))
    finally:
        shutil.rmtree(stub_dir, ignore_errors=True)


# Stages whose params section has `processes`: worker processes that train side by side.
PROCESS_STAGES = ("train_specialist", "train_pderl")


def stage_processes(params: dict[str, Any], stage: str) -> int:
    """How many processes one task of `stage` runs at once under the cell's params (1 for a
    stage without workers); the section's default is 1."""
    if stage not in PROCESS_STAGES:
        return 1
    return max(1, int((params.get(stage) or {}).get("processes", 1)))


def _resources(grid: Grid, stage: str, cluster_gpus: float, processes: int = 1) -> tuple[float, float, int]:
    """(CPUs, GPUs, torch threads per process) of one task. A stage that runs `processes`
    worker processes reserves that many CPUs unless the grid says otherwise, and its threads
    default to the reserved CPUs shared among its processes."""
    spec = grid.resources.get(stage, ResourceSpec())
    cpus = spec.cpus if "cpus" in spec.model_fields_set else float(processes)
    gpus = spec.gpus
    if gpus == "auto":
        gpus = 1.0 if cluster_gpus > 0 and stage in GPU_STAGES else 0.0
    threads = spec.threads or max(1, int(cpus) // processes)
    return cpus, float(gpus), threads


def _import_ray():
    try:
        import ray
    except ImportError:
        raise SweepError(f"Ray is not installed; it is an optional extra: {SWEEP_EXTRA}") from None
    return ray


def run_sweep(
    grid_path: Path,
    remote: str,
    *,
    repo: Path = Path("."),
    workdir: Path | None = None,
    address: str | None = None,
    workers: int | None = None,
    max_retries: int = 3,
    git_url: str | None = None,
    scratch: str | None = None,
    dry_run: bool = False,
    remote_options: dict[str, str] | None = None,
    resume_root: Path | None = None,
    log: Callable[[str], None] = lambda line: None,
) -> list[CellResult]:
    """Run a grid: prepare one workspace per cell, run every stage item as a Ray task, write each
    completed cell's dvc.lock. Progress lines go to `log` (the command passes typer.echo).
    Returns one CellResult per cell; raises SweepError(exit_code=1) when any stage failed, after
    the other cells completed."""
    grid_path = Path(grid_path)
    grid = load_grid(grid_path)
    options = tuple(sorted((remote_options or {}).items()))
    bad = [k for k, _ in options if not re.fullmatch(r"[a-z_]+", k)]
    if bad:
        raise SweepError(f"--remote-option: {bad} are not DVC remote setting names (e.g. endpointurl, access_key_id)", 2)
    repo = _repo_root(Path(repo).resolve())
    commit = _git(repo, "rev-parse", "HEAD").strip()
    _check_clean(repo, commit)
    cells = plan_cells(grid, grid_path, repo, commit)
    source = git_url or str(repo)
    if "://" not in remote:  # a directory (a URL such as s3://... is passed to DVC as is)
        remote_path = Path(remote).expanduser().resolve()
        remote_path.mkdir(parents=True, exist_ok=True)
        remote = str(remote_path)
    workdir = (Path(workdir) if workdir is not None else repo / "sweeps" / grid_path.stem).resolve()
    log(f"sweep {grid_path.name}: {len(cells)} cell(s), code commit {commit[:12]}, remote {remote}, workspaces in {workdir}")

    plans: list[CellPlan] = []
    results: dict[str, CellResult] = {}
    for cell in cells:
        ws = workdir / cell.name
        fresh = prepare_workspace(ws, cell, source, commit, grid.targets)
        plan = CellPlan(cell, ws, fresh)
        results[cell.name] = CellResult(cell.name, ws)
        if fresh:
            results[cell.name].status = "up to date"
            log(f"  {cell.name}: up to date, nothing to run")
        else:
            try:
                plan.items = stage_items(ws, grid.targets)
            except ValueError as exc:
                raise GridError(f"{grid_path}: targets: {exc}") from None
            except Exception as exc:  # noqa: BLE001 - DVC's own errors (dvc.yaml vs the cell's params)
                raise SweepError(f"cell {cell.name}: DVC cannot read the pipeline in {ws}: {exc}") from None
            known = {i.stage for i in plan.items} | set(GPU_STAGES)
            unknown = sorted(set(grid.resources) - known)
            if unknown:
                raise GridError(f"{grid_path}: resources: {unknown} are not dvc.yaml stages (have {sorted({i.stage for i in plan.items})})")
            log(f"  {cell.name}: {len(plan.items)} stage items")
        plans.append(plan)
    todo = [p for p in plans if not p.up_to_date]
    if dry_run:
        for p in todo:
            results[p.cell.name].status = "planned"
            for it in p.items:
                log(f"    {p.cell.name} {it.name}  <- {', '.join(it.upstream) or '-'}")
        return list(results.values())
    if not todo:
        log("nothing to run")
        return list(results.values())

    ray = _import_ray()
    started = False
    if not ray.is_initialized():
        try:
            if address:
                ray.init(address=address, log_to_driver=False)
            else:
                ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
        except Exception as exc:  # noqa: BLE001 - no cluster at that address, bad address, ...
            raise SweepError(f"cannot start or reach Ray ({'address ' + address if address else 'local'}): {exc}") from None
        started = True
    try:
        cluster = ray.cluster_resources()
        log(f"ray: {cluster.get('CPU', 0):g} CPU, {cluster.get('GPU', 0):g} GPU, {len(ray.nodes())} node(s)")
        remote_fn = ray.remote(run_stage_task)
        # one task per distinct computation: an item whose signature another cell already has
        # shares that cell's task (DVC would give both the same run-cache key)
        by_signature: dict[str, Any] = {}
        pending: dict[Any, list[tuple[str, StageItem]]] = {}
        for p in todo:
            refs: dict[str, Any] = {}
            for it in p.items:
                if it.signature in by_signature:
                    ref = by_signature[it.signature]
                else:
                    cpus, gpus, threads = _resources(grid, it.stage, cluster.get("GPU", 0), stage_processes(p.cell.params, it.stage))
                    task = StageTask(
                        p.cell.name, it.name, source, commit, p.cell.params_text, remote, it.pull, threads, gpus, scratch,
                        options, str(Path(resume_root).resolve()) if resume_root else None,
                    )
                    ref = remote_fn.options(
                        num_cpus=cpus, num_gpus=gpus, max_retries=max_retries, retry_exceptions=False,
                        name=f"{p.cell.name}:{it.name}",
                    ).remote(task, *[refs[u] for u in it.upstream])
                    by_signature[it.signature] = ref
                refs[it.name] = ref
                pending.setdefault(ref, []).append((p.cell.name, it))
        total, done = len(pending), 0
        t0 = time.monotonic()
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                owners = pending.pop(ref)
                (cell_name, it), others = owners[0], [c for c, _ in owners[1:]]
                shared = f" (shared with {', '.join(others)})" if others else ""
                done += 1
                try:
                    r: StageResult = ray.get(ref)
                except Exception as exc:  # noqa: BLE001 - RayTaskError, WorkerCrashedError, ...
                    cause = getattr(exc, "cause", None)
                    if isinstance(cause, StageFailed) and cause.item != it.name:
                        msg = f"not run: upstream {cause.item} failed"
                        log(f"[{done}/{total}] {cell_name} {it.name}{shared}: {msg}")
                    else:
                        msg = cause.detail if isinstance(cause, StageFailed) else f"{type(exc).__name__}: {exc}"
                        log(f"[{done}/{total}] {cell_name} {it.name}{shared}: FAILED\n{msg}")
                    for c, _ in owners:
                        results[c].failed[it.name] = msg
                    continue
                for c, _ in owners:
                    (results[c].executed if r.executed else results[c].restored).append(it.name)
                how = "ran" if r.executed else "restored from the run-cache"
                split = ", ".join(f"{k} {v:.1f}" for k, v in r.phases.items())
                log(
                    f"[{done}/{total}] {cell_name} {it.name}{shared}: {how} in {r.seconds:.1f} s on {r.host} "
                    f"({split}); {time.monotonic() - t0:.0f} s elapsed"
                )
    finally:
        if started:
            ray.shutdown()

    for p in todo:
        res = results[p.cell.name]
        if res.failed:
            res.status = "failed"
            continue
        try:
            write_lock(p.workspace, remote, grid.targets, options)
        except RuntimeError as exc:
            res.status = "failed"
            res.failed["dvc.lock"] = str(exc)
            log(f"  {p.cell.name}: writing dvc.lock failed:\n{exc}")
            continue
        res.status = "done"
        log(f"  {p.cell.name}: dvc.lock written ({len(res.executed)} ran, {len(res.restored)} restored) in {p.workspace}")
    failed = [r for r in results.values() if r.status == "failed"]
    if failed:
        lines = [f"{r.name}: {', '.join(sorted(r.failed))}" for r in failed]
        raise SweepError("stages failed in " + "; ".join(lines) + " (fix the cause and rerun the sweep: completed stages are restored, not recomputed)", exit_code=1)
    return list(results.values())
