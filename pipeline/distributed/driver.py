"""The driver: run_sweep plans the grid's cells and their workspaces, submits one Ray task per
distinct stage item (sharing a task between cells whose item is one DVC computation), collects
the results as they finish, and writes each completed cell's dvc.lock. Ray is imported only
here, and only when a sweep runs tasks."""

from __future__ import annotations

import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

from pipeline.distributed.errors import GridError, StageFailed, SweepError
from pipeline.distributed.grid import Cell, Grid, ResourceSpec, load_grid, plan_cells, with_seeds
from pipeline.distributed.task import StageResult, StageTask, run_stage_task
from pipeline.distributed.workspace import StageItem, _git, prepare_workspace, stage_items, write_lock

SWEEP_EXTRA = 'pip install -e ".[sweep]"'


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
    dirty = [
        line
        for line in _git(repo, "status", "--porcelain", "--untracked-files=no", "--", ".", ":!dvc.lock").splitlines()
        if line
    ]
    if dirty:
        files = ", ".join(line[3:] for line in dirty[:10]) + (", ..." if len(dirty) > 10 else "")
        raise SweepError(
            f"{repo} has uncommitted changes ({files}); workers run commit {commit[:12]}, so commit them first"
        )


# Stages whose params section has `processes`: worker processes that train side by side.
PROCESS_STAGES = ("train_specialist", "train_pderl")


def stage_processes(params: dict[str, Any], stage: str) -> int:
    """How many processes one task of `stage` runs at once under the cell's params (1 for a
    stage without workers); the section's default is 1."""
    if stage not in PROCESS_STAGES:
        return 1
    return max(1, int((params.get(stage) or {}).get("processes", 1)))


def _resources(
    grid: Grid, stage: str, cluster_gpus: float, processes: int = 1, on_device: bool = False
) -> tuple[float, float, int]:
    """(CPUs, GPUs, torch threads per process) of one task. A stage that runs `processes`
    worker processes reserves that many CPUs unless the grid says otherwise, and its threads
    default to the reserved CPUs shared among its processes. Under `gpus: auto` an item that
    computes on a device (`on_device`: pipeline.distributed.workspace.wants_device, from the
    params it lists) gets one GPU where the cluster has any."""
    spec = grid.resources.get(stage, ResourceSpec())
    cpus = spec.cpus if "cpus" in spec.model_fields_set else float(processes)
    gpus = spec.gpus
    if gpus == "auto":
        gpus = 1.0 if cluster_gpus > 0 and on_device else 0.0
    threads = spec.threads or max(1, int(cpus) // processes)
    return cpus, float(gpus), threads


def _import_ray():
    try:
        import ray
    except ImportError:
        raise SweepError(f"Ray is not installed; it is an optional extra: {SWEEP_EXTRA}") from None
    return ray


@dataclass(frozen=True)
class SweepSettings:
    """How a sweep runs, as `mapex repro --ray`'s options give it (one place: the command builds it, the
    driver and the task submission read it). `remote` is a directory or a URL; `remote_options`
    are extra DVC remote settings (KEY=VALUE, written to each workspace's config.local)."""

    remote: str
    repo: Path = Path(".")
    workdir: Path | None = None
    address: str | None = None
    workers: int | None = None
    max_retries: int = 3
    git_url: str | None = None
    scratch: str | None = None
    dry_run: bool = False
    remote_options: dict[str, str] = field(default_factory=dict)
    resume_root: Path | None = None
    seeds: list[int] | None = None


def run_sweep(
    grid_path: Path, settings: SweepSettings, log: Callable[[str], None] = lambda line: None
) -> list[CellResult]:
    """Run a grid: prepare one workspace per cell, run every stage item as a Ray task, write each
    completed cell's dvc.lock. Progress lines go to `log` (the command passes typer.echo).
    Returns one CellResult per cell; raises SweepError(exit_code=1) when any stage failed, after
    the other cells completed."""
    grid_path = Path(grid_path)
    grid = load_grid(grid_path)
    if settings.seeds:
        grid = with_seeds(grid, grid_path, settings.seeds)
    options = _remote_settings(settings.remote_options)
    repo = _repo_root(Path(settings.repo).resolve())
    commit = _git(repo, "rev-parse", "HEAD").strip()
    _check_clean(repo, commit)
    cells = plan_cells(grid, grid_path, repo, commit)
    source = settings.git_url or str(repo)
    remote = _remote_location(settings.remote)
    workdir = (Path(settings.workdir) if settings.workdir is not None else repo / "sweeps" / grid_path.stem).resolve()
    log(
        f"sweep {grid_path.name}: {len(cells)} cell(s), code commit {commit[:12]}, remote {remote}, workspaces in {workdir}"
    )

    plans, results = _plan_workspaces(grid, grid_path, cells, workdir, source, commit, log)
    todo = [p for p in plans if not p.up_to_date]
    if settings.dry_run:
        _log_plan(todo, results, log)
        return list(results.values())
    if not todo:
        log("nothing to run")
        return list(results.values())

    ray = _import_ray()
    started = _start_ray(ray, settings.address, settings.workers)
    try:
        cluster = ray.cluster_resources()
        log(f"ray: {cluster.get('CPU', 0):g} CPU, {cluster.get('GPU', 0):g} GPU, {len(ray.nodes())} node(s)")
        pending = _submit_tasks(
            ray,
            todo,
            grid,
            cluster.get("GPU", 0),
            settings,
            source=source,
            commit=commit,
            remote=remote,
            options=options,
        )
        _collect_results(ray, pending, results, log)
    finally:
        if started:
            ray.shutdown()

    _write_locks(todo, results, remote, grid.targets, options, log)
    _raise_if_failed(results)
    return list(results.values())


def _remote_settings(remote_options: dict[str, str] | None) -> tuple[tuple[str, str], ...]:
    """The --remote-option settings, sorted; a key that is no DVC setting name is refused."""
    options = tuple(sorted((remote_options or {}).items()))
    bad = [k for k, _ in options if not re.fullmatch(r"[a-z_]+", k)]
    if bad:
        raise SweepError(
            f"--remote-option: {bad} are not DVC remote setting names (e.g. endpointurl, access_key_id)", 2
        )
    return options


def _remote_location(remote: str) -> str:
    """The remote as DVC gets it: a directory made absolute (and created), a URL as is."""
    if "://" not in remote:  # a directory (a URL such as s3://... is passed to DVC as is)
        remote_path = Path(remote).expanduser().resolve()
        remote_path.mkdir(parents=True, exist_ok=True)
        remote = str(remote_path)
    return remote


def _plan_workspaces(
    grid: Grid, grid_path: Path, cells: list[Cell], workdir: Path, source: str, commit: str, log: Callable[[str], None]
) -> tuple[list[CellPlan], dict[str, CellResult]]:
    """Prepare every cell's workspace under `workdir` and read the stage items of those not up to
    date; returns the plans and a pending CellResult per cell (up to date ones marked so)."""
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
            known = {i.stage for i in plan.items} | _stage_names(ws)
            unknown = sorted(set(grid.resources) - known)
            if unknown:
                raise GridError(
                    f"{grid_path}: resources: {unknown} are not dvc.yaml stages (have {sorted({i.stage for i in plan.items})})"
                )
            log(f"  {cell.name}: {len(plan.items)} stage items")
        plans.append(plan)
    return plans, results


def _log_plan(todo: list[CellPlan], results: dict[str, CellResult], log: Callable[[str], None]) -> None:
    """--dry-run: mark the cells to run as planned and log each stage item with its upstream."""
    for p in todo:
        results[p.cell.name].status = "planned"
        for it in p.items:
            log(f"    {p.cell.name} {it.name}  <- {', '.join(it.upstream) or '-'}")


def _stage_names(ws: Path) -> set[str]:
    """Every stage the pipeline knows in workspace `ws`, those the cell's plan leaves out
    included: its stage catalogue's stages and a stage per built-in method (the catalogue's
    method templates are not stages: the plan writes one stage per method from them)."""
    from pipeline.params.methods import METHODS
    from pipeline.params.plan import TEMPLATES, stage_blocks

    try:
        _, blocks, _ = stage_blocks((ws / "pipeline" / "params" / "stage_catalogue.yaml").read_text())
    except (OSError, ValueError):
        return set()
    return {name for name, _ in blocks if name not in TEMPLATES} | set(METHODS)


def _start_ray(ray, address: str | None, workers: int | None) -> bool:
    """Connect to the cluster at `address`, or start a local one; returns whether it did (False:
    Ray was already initialised by the caller, whose cluster is left running)."""
    if ray.is_initialized():
        return False
    try:
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
    except Exception as exc:  # noqa: BLE001 - no cluster at that address, bad address, ...
        raise SweepError(f"cannot start or reach Ray ({'address ' + address if address else 'local'}): {exc}") from None
    return True


def _submit_tasks(
    ray,
    todo: list[CellPlan],
    grid: Grid,
    cluster_gpus: float,
    settings: SweepSettings,
    *,
    source: str,
    commit: str,
    remote: str,
    options: tuple[tuple[str, str], ...],
) -> dict[Any, list[tuple[str, StageItem]]]:
    """Submit the stage items of every cell to run as Ray tasks, each after its upstream's;
    returns each task's ref -> the (cell, item) pairs it computes. `source`, `commit`, `remote`
    and `options` are the settings as run_sweep resolved them (clone URL, HEAD, absolute remote,
    checked remote options)."""
    resume_root = str(Path(settings.resume_root).resolve()) if settings.resume_root else None
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
                cpus, gpus, threads = _resources(
                    grid, it.stage, cluster_gpus, stage_processes(p.cell.params, it.stage), it.on_device
                )
                task = StageTask(
                    p.cell.name,
                    it.name,
                    source,
                    commit,
                    p.cell.params_text,
                    remote,
                    it.pull,
                    threads,
                    gpus,
                    settings.scratch,
                    options,
                    resume_root,
                    it.sources,
                )
                ref = remote_fn.options(
                    num_cpus=cpus,
                    num_gpus=gpus,
                    max_retries=settings.max_retries,
                    retry_exceptions=False,
                    name=f"{p.cell.name}:{it.name}",
                ).remote(task, *[refs[u] for u in it.upstream])
                by_signature[it.signature] = ref
            refs[it.name] = ref
            pending.setdefault(ref, []).append((p.cell.name, it))
    return pending


def _collect_results(
    ray, pending: dict[Any, list[tuple[str, StageItem]]], results: dict[str, CellResult], log: Callable[[str], None]
) -> None:
    """Wait for every task, in the order they finish: record each item as executed, restored or
    failed in its cells' results (`pending` is emptied) and log one progress line per task."""
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


def _write_locks(
    todo: list[CellPlan],
    results: dict[str, CellResult],
    remote: str,
    targets: list[str] | None,
    options: tuple[tuple[str, str], ...],
    log: Callable[[str], None],
) -> None:
    """Write the dvc.lock of every cell whose tasks all succeeded; mark each cell done or failed."""
    for p in todo:
        res = results[p.cell.name]
        if res.failed:
            res.status = "failed"
            continue
        try:
            write_lock(p.workspace, remote, targets, options)
        except RuntimeError as exc:
            res.status = "failed"
            res.failed["dvc.lock"] = str(exc)
            log(f"  {p.cell.name}: writing dvc.lock failed:\n{exc}")
            continue
        res.status = "done"
        log(
            f"  {p.cell.name}: dvc.lock written ({len(res.executed)} ran, {len(res.restored)} restored) in {p.workspace}"
        )


def _raise_if_failed(results: dict[str, CellResult]) -> None:
    """SweepError(exit_code=1) naming each failed cell and its failed items, if any failed."""
    failed = [r for r in results.values() if r.status == "failed"]
    if failed:
        lines = [f"{r.name}: {', '.join(sorted(r.failed))}" for r in failed]
        raise SweepError(
            "stages failed in "
            + "; ".join(lines)
            + " (fix the cause and rerun the sweep: completed stages are restored, not recomputed)",
            exit_code=1,
        )
