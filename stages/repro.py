"""`mapex repro [PLAN]`: the one way to run a plan (this checkout's params.yaml, a preset or a
grid), its stage items side by side on this machine, or on Ray with --ray and --remote.

Not a DVC stage: it drives DVC (pipeline/distributed/local.py says how items run side by side and
why it is safe; pipeline/distributed/onebox.py how a grid's cells run here; driver.py on Ray).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Optional

import typer
import yaml

from pipeline.distributed.local import Terminated, repro_parallel, summary_table
from pipeline.distributed.workspace import _dvc_bin, stage_items
from stages.common import reports_errors

# The default's ceiling: each item is a process of about 0.5 GB (torch) and may start workers of
# its own (processes: 2), so more than 8 at once buys little on the quickstart's chains (two
# seeds) and risks a laptop's memory; --jobs sets any number.
MAX_DEFAULT_JOBS = 8


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


PLAN_SUFFIXES = (".yaml", ".yml")


def split_plan(args: list[str]) -> tuple[Path | None, list[str]]:
    """`mapex repro`'s positional arguments as (PLAN, targets): a first argument naming a YAML
    file is the plan, the rest (or all, without one) are stage targets."""
    if args and args[0].endswith(PLAN_SUFFIXES):
        return Path(args[0]), list(args[1:])
    return None, list(args)


def _replan_if_stale(root: Path) -> None:
    """Write dvc.yaml again when it was planned for other params (the plan is generated from
    params.yaml: rewriting it is this command's job, not the user's); one line says so."""
    from pipeline.params import load_params
    from pipeline.params.plan import write_plan
    from pipeline.params.planned import stale_input

    params, dvc = root / "params.yaml", root / "dvc.yaml"
    if not params.is_file() or not dvc.is_file():
        return
    raw = load_params(params, check_plan=False)
    why = stale_input(raw, dvc.read_text())
    if why and "stale:" in why:
        write_plan(raw, params)  # as `mapex plan` does
        typer.echo(f"{dvc}: {why.split(': run')[0]}; planned again from {params}", err=True)


@reports_errors
def repro(
    args: Optional[list[str]] = typer.Argument(
        None,
        metavar="[PLAN] [TARGETS]...",
        help="PLAN: params.yaml (the default: this checkout's pipeline), a preset or a grid file "
        "(each cell in a workspace of its own under --workdir; a preset is a grid of one cell and is "
        "never copied over params.yaml). TARGETS: stages or stage items to reproduce with everything "
        "upstream of them (default: all)",
    ),
    jobs: int = typer.Option(
        0,
        "--jobs",
        "-j",
        min=0,
        help="stage items at most side by side (default 0: one per core of this machine, at most 8); 1 is plain `dvc repro`",
    ),
    root: Path = typer.Option(Path("."), "--root", help="the DVC workspace (the repository root)"),
    workdir: Optional[Path] = typer.Option(
        None,
        "--workdir",
        help="with a preset or grid: where each cell's workspace goes (default: sweeps/<PLAN name>)",
    ),
    seed: Optional[list[int]] = typer.Option(
        None, "--seed", min=0, help="with a preset or grid: run only this seed (repeatable) instead of its seeds"
    ),
    ray: Optional[str] = typer.Option(
        None,
        "--ray",
        metavar="ADDRESS",
        help="with a grid or preset: run its stage items as tasks on this Ray cluster ('auto', host:6379, "
        "or 'local' to start one on this machine), one DVC workspace per cell under --workdir and the artifacts "
        "in --remote; workers run --root's HEAD commit, so commit first (docs/sweeps.md)",
    ),
    remote: Optional[str] = typer.Option(
        None,
        "--remote",
        help="with --ray: the shared DVC remote every worker reaches, holding every output and the run-cache: "
        "a directory (created if missing) or a URL such as s3://bucket/path",
    ),
    workers: Optional[int] = typer.Option(
        None, "--workers", min=1, help="with --ray local: CPUs of the local Ray cluster (default: every core)"
    ),
    git_url: Optional[str] = typer.Option(
        None,
        "--git-url",
        help="with --ray: where workers clone --root's HEAD commit from (default: --root's path, fine on one "
        "machine or a shared filesystem; else a git URL every node can reach)",
    ),
    scratch: Optional[str] = typer.Option(
        None,
        "--scratch",
        help="with --ray: directory on each worker for its temporary clones (default: <tmp>/mapex-sweep)",
    ),
    max_retries: int = typer.Option(
        3,
        "--max-retries",
        min=0,
        help="with --ray: retries of a task whose worker or node died; a stage that exits with an error is not retried",
    ),
    dry_run: bool = typer.Option(
        False, "--dry-run", help="with --ray: prepare the cells' workspaces, print every cell's stage items and stop"
    ),
    resume_root: Optional[Path] = typer.Option(
        None,
        "--resume-root",
        help="with --ray: a directory every node reaches (shared filesystem) where long stages keep their resume "
        "progress, one folder per stage item, so a task retried after its node died resumes there "
        "(default: progress lives in the worker's clone and dies with it)",
    ),
    remote_option: Optional[list[str]] = typer.Option(
        None,
        "--remote-option",
        help="with --ray: KEY=VALUE setting of the DVC remote besides its URL, repeatable; e.g. for an "
        "S3-compatible server endpointurl=http://host:9000 (credentials: access_key_id, secret_access_key, or the "
        "usual AWS_* environment on every node). Written to each workspace's .dvc/config.local, never to git",
    ),
) -> None:
    """Reproduce a plan: this checkout's pipeline, a preset or a grid, its stage items side by side.

    Each stage item runs as `dvc repro --single-item ITEM` once every item upstream of it has
    finished, at most --jobs at a time: on 2 cores the two seeds' extractions, evaluations and
    scores run together instead of one after another. DVC decides for each item, as in `dvc
    repro`, whether it reruns, is restored from the run-cache or is skipped as unchanged, and the
    outputs are the same bytes (every stage is a pure command; one torch thread a process).
    Without PLAN (or with params.yaml) it runs this checkout's dvc.yaml, planned again first if
    params.yaml changed what runs. With a preset or a grid, each cell is a clone of the commit
    under --workdir with its params.yaml and dvc.yaml, all cells sharing this checkout's DVC
    cache (an item two cells share runs once); a grid of several cells ends with its cross-cell
    report in WORKDIR/report. Items' output goes to .dvc/tmp/mapex-repro/ITEM.log of their
    workspace; a line here as each starts and ends, the end of a failed item's log, and a table
    of every item's wall time at the end. After a failure nothing new starts; Ctrl-C (or
    SIGTERM) reaches the running items, which stop as under `dvc repro` (nothing half-written);
    it exits 130 (143).

    With --ray and --remote the cells' stage items run as Ray tasks, each `dvc repro
    --single-item --pull` in a clone of its own that pushes outputs and run-cache to the remote;
    each cell's dvc.lock is then written once, restoring every stage from the run-cache. Run it
    again to resume: finished items are restored, not recomputed.
    """
    plan, targets = split_plan(list(args or []))
    cluster = {
        "workers": workers,
        "git_url": git_url,
        "scratch": scratch,
        "max_retries": max_retries,
        "dry_run": dry_run,
        "resume_root": resume_root,
        "remote_options": _remote_options(remote_option or []),
    }
    given = [
        flag
        for flag, value in (
            ("--workers", workers),
            ("--git-url", git_url),
            ("--scratch", scratch),
            ("--max-retries", max_retries != 3 or None),
            ("--dry-run", dry_run or None),
            ("--resume-root", resume_root),
            ("--remote-option", remote_option),
        )
        if value
    ]
    if given and not ray:
        typer.echo(f"error: {', '.join(given)} go with --ray (a run on a Ray cluster)", err=True)
        raise typer.Exit(code=2)
    if plan is not None and plan.name != "params.yaml":
        _repro_plan(plan, root, jobs, targets, workdir, seed, ray, remote, cluster)
        return
    if ray or remote or workdir or seed:
        typer.echo("error: --ray, --remote, --workdir and --seed go with a preset or grid PLAN", err=True)
        raise typer.Exit(code=2)
    if plan is not None:
        root = plan.parent
    jobs = jobs or min(_cores(), MAX_DEFAULT_JOBS)
    if not (root / "dvc.yaml").is_file():
        raise FileNotFoundError(f"{root / 'dvc.yaml'}: no dvc.yaml here (--root names the DVC workspace)")
    _replan_if_stale(root)
    if jobs == 1:
        rc = subprocess.call([_dvc_bin(), "repro", *(targets or [])], cwd=root)
        raise typer.Exit(code=rc)
    try:
        items = stage_items(root, list(targets) if targets else None)
    except (ValueError, LookupError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(code=2) from None
    typer.echo(f"{len(items)} stage items, at most {jobs} side by side (logs: .dvc/tmp/mapex-repro/)", err=True)
    _finish(lambda: repro_parallel(root, items, jobs, echo=lambda line: typer.echo(line, err=True)))


def _finish(run) -> None:
    """Run `run` (a repro_parallel call), then print its table; the exit codes of an interrupt,
    a SIGTERM or a failed item."""
    try:
        result = run()
    except KeyboardInterrupt:
        typer.echo("stopped: the running stage items were interrupted; rerun to go on", err=True)
        raise typer.Exit(code=130) from None
    except Terminated:
        typer.echo("stopped by SIGTERM: it reached the running stage items; rerun to go on", err=True)
        raise typer.Exit(code=143) from None
    if result is None:
        return
    typer.echo(summary_table(result), err=True)
    if result.failed:
        names = ", ".join(r.name for r in result.failed)
        left = f"; not started: {', '.join(result.not_started)}" if result.not_started else ""
        typer.echo(f"error: {names} failed{left}", err=True)
        raise typer.Exit(code=1)


def _repro_plan(
    plan: Path,
    root: Path,
    jobs: int,
    targets: list[str],
    workdir: Path | None,
    seeds: list[int] | None,
    ray: str | None,
    remote: str | None,
    cluster: dict,
) -> None:
    """A preset or grid: its cells on Ray (--ray, --remote; `cluster` holds the other options of a
    Ray run, as SweepSettings names them) or here, then its report."""
    from pipeline.distributed.errors import SweepError
    from pipeline.distributed.onebox import load_plan, run_plan_here

    echo = lambda line: typer.echo(line, err=True)  # noqa: E731
    try:
        if ray or remote:
            if not (ray and remote):
                raise SweepError("--ray and --remote go together: the cluster's workers share the remote", 2)
            if targets:
                raise SweepError("with --ray the grid file's `targets` say what runs (no TARGETS here)", 2)
            from pipeline.distributed.driver import SweepSettings, run_sweep

            grid_path = plan
            if "envs" not in (yaml.safe_load(plan.read_text()) or {}):
                grid_path = _one_cell_grid(plan, root)
            if cluster["workers"] and ray != "local":
                raise SweepError("--workers sizes a local Ray cluster (--ray local); a cluster has its own CPUs", 2)
            settings = SweepSettings(
                remote,
                repo=root,
                workdir=workdir or Path(root) / "sweeps" / plan.stem,
                address=None if ray == "local" else ray,
                seeds=seeds,
                **cluster,
            )
            results = run_sweep(grid_path, settings, log=echo)
            for r in results:
                echo(f"{r.name}: {r.status} ({len(r.executed)} ran, {len(r.restored)} restored) {r.workspace}")
            if settings.dry_run:
                return
            names = [r.name for r in results]
            work = settings.workdir
        else:
            jobs = jobs or min(_cores(), MAX_DEFAULT_JOBS)
            load_plan(plan, Path(root).resolve())  # a bad plan file is named before anything else
            out = run_plan_here(plan, root, jobs, workdir=workdir, seeds=seeds, targets=targets or None, log=echo)
            names, work = out.cells, out.workdir
            _finish(lambda: out.repro)
    except SweepError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(code=exc.exit_code) from None
    _report(Path(work), names)


def _remote_options(items: list[str]) -> dict[str, str]:
    """--remote-option KEY=VALUE pairs as a dict; a malformed one stops the run (exit 2)."""
    options = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            typer.echo(f"error: --remote-option {item!r}: expected KEY=VALUE", err=True)
            raise typer.Exit(code=2)
        options[key.strip()] = value.strip()
    return options


def _one_cell_grid(preset: Path, root: Path) -> Path:
    """A grid file of one cell for a preset (--ray), in the checkout's .dvc/tmp (never tracked)."""
    from pipeline.distributed.onebox import load_plan

    grid, _ = load_plan(preset, Path(root).resolve())
    path = Path(root) / ".dvc" / "tmp" / "mapex-repro" / f"{preset.stem}.grid.yaml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(grid.model_dump(exclude_defaults=True), sort_keys=False))
    return path


def _report(workdir: Path, cells: list[str]) -> None:
    """Where the report is: a cell's own, or for several cells their cross-cell report, written
    to WORKDIR/report (as `mapex grid-report WORKDIR --out WORKDIR/report`)."""
    if len(cells) == 1:
        typer.echo(f"report: {workdir / cells[0] / 'data' / 'report' / 'report.md'}", err=True)
        return
    if not all((workdir / c / "data" / "score").is_dir() for c in cells):
        typer.echo(f"no cross-cell report: not every cell of {workdir} was scored (targets)", err=True)
        return
    # the command itself, as a user runs it (a stage command never imports another's module)
    mapex = Path(sys.executable).with_name("mapex")
    rc = subprocess.call(
        [str(mapex) if mapex.is_file() else "mapex", "grid-report", str(workdir), "--out", str(workdir / "report")]
    )
    if rc != 0:
        raise typer.Exit(code=rc)
