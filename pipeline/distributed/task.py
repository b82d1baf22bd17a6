"""The Ray task: what runs on a worker for one stage item (a fresh clone of the commit with the
cell's params and its upstream's dvc.lock entries, `dvc repro --single-item --pull`, the push of
its outputs and run-cache entry), with its argument and result types. Plain Python, so it is
testable without Ray; the driver wraps run_stage_task with `ray.remote`."""

from __future__ import annotations

import os
import re
import shutil
import socket
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from pipeline.core.resume import RESUME_ROOT_ENV
from pipeline.distributed.errors import StageFailed, SweepError
from pipeline.distributed.workspace import _clone_at, _run_dvc, checkout_cell, configure_remote

# Test hook: "<cell>/<item>=<marker file>" makes that task's worker die (os._exit) once, after its
# stage ran and before it published anything, the worst moment for a worker to die.
DIE_ONCE_ENV = "MAPEX_SWEEP_TEST_DIE_ONCE"


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
    sources: tuple[str, ...] = ()  # .dvc files of `dvc add`ed data it reads (StageItem.sources), pulled first


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
        if d.name.startswith(prefix) and d.name[len(prefix) :].isdigit():
            try:
                os.kill(int(d.name[len(prefix) :]), 0)
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


def _pull_upstream(clone: Path, env: dict[str, str], task: StageTask) -> None:
    """Pull the outputs of every upstream item in the clone's dvc.lock (which holds only those),
    then check that each path of task.pull arrived.

    One target, the dvc.yaml file: DVC parses dvc.yaml and dvc.lock once. Given the outputs as
    path targets instead, it re-parsed both for every path, twice (fetch, then checkout): about
    2.3 s a path with 40-60 upstream entries in the lock, 374 s for a 5-seed report's 160 paths
    (docs/benchmarks.md, "Sweep: pulling a report's inputs"). This pulls a little more than
    task.pull (every output of those upstream items, such as the populations beside the
    provenance a report reads), none of it large next to what the stages write. --allow-missing:
    the stages of dvc.yaml that are not upstream have no lock entry, so nothing to pull; whether
    the outputs this item needs arrived is checked below, by name. Data the user tracked with `dvc
    add` (task.sources: an imported model's .dvc file) is pulled by its .dvc file, in the same call."""
    lock = (clone / "dvc.lock").is_file() or not task.sources  # no upstream item: no lock, only the data
    targets = (["dvc.yaml"] if lock else []) + list(task.sources)
    _run_dvc(clone, env, "pull", "--quiet", "--allow-missing", *targets)
    missing = [p for p in task.pull if not (clone / p).exists()]
    if missing:
        shown = ", ".join(missing[:5]) + (f" and {len(missing) - 5} more" if len(missing) > 5 else "")
        raise RuntimeError(
            f"{len(missing)} upstream output(s) not in the remote {task.remote} after `dvc pull`: {shown}"
        )


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
                _pull_upstream(clone, env, task)
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
            raise StageFailed(
                task.cell, task.item, "no run-cache entry matches its dvc.lock entry (is every out cached?)"
            )
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
