"""`mapex sweep`: run a grid of pipeline runs on Ray, a shared DVC remote holding the artifacts.

Not a DVC stage: it drives DVC. The library is pipeline/distributed/ (run_sweep in driver.py); the guide is docs/sweeps.md.
Ray is an optional extra (pip install -e ".[sweep]") imported only when a sweep runs.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from pipeline.distributed.driver import SweepSettings, run_sweep
from pipeline.distributed.errors import SweepError
from stages.common import reports_errors


@reports_errors
def sweep(
    grid: Path = typer.Argument(
        ...,
        help="grid file (YAML): envs (ids, preset files or mappings), seeds, named param override sets, "
        "targets, per-stage resources; see docs/sweeps.md",
    ),
    remote: str = typer.Option(
        ...,
        "--remote",
        help="shared DVC remote every worker can reach: a directory (created if missing) or a URL "
        "such as s3://bucket/path; holds every output and the run-cache",
    ),
    address: Optional[str] = typer.Option(
        None,
        "--address",
        help="Ray cluster to run on ('auto', or host:6379 of a `ray start --head`); "
        "default: start a local one on this machine",
    ),
    workers: Optional[int] = typer.Option(
        None, "--workers", min=1, help="CPUs of the local Ray cluster (default: every core); ignored with --address"
    ),
    workdir: Optional[Path] = typer.Option(
        None,
        "--workdir",
        help="where the driver keeps one DVC workspace per grid cell, with its dvc.lock and "
        "outputs (default: sweeps/<grid file name> in the repository)",
    ),
    repo: Path = typer.Option(
        Path("."), "--repo", help="the project checkout; workers run its HEAD commit, so commit first"
    ),
    git_url: Optional[str] = typer.Option(
        None,
        "--git-url",
        help="where workers clone that commit from (default: --repo's path, fine on one machine or a "
        "shared filesystem; else a git URL every node can reach)",
    ),
    scratch: Optional[str] = typer.Option(
        None, "--scratch", help="directory on each worker for its temporary clones (default: <tmp>/mapex-sweep)"
    ),
    max_retries: int = typer.Option(
        3,
        "--max-retries",
        min=0,
        help="retries of a task whose worker or node died; a stage that exits with an error is not retried",
    ),
    dry_run: bool = typer.Option(
        False, "--dry-run", help="prepare the workspaces, print every cell's stage items and stop"
    ),
    resume_root: Optional[Path] = typer.Option(
        None,
        "--resume-root",
        help="a directory every node can reach (shared filesystem) where long stages keep their "
        "resume progress, one folder per stage item: a task retried after its node died resumes there instead of "
        "starting over (default: progress lives in the worker's clone and dies with it)",
    ),
    seed: Optional[list[int]] = typer.Option(
        None,
        "--seed",
        min=0,
        help="run only this seed instead of the grid's seeds (repeatable): a first look at a long grid; "
        "a later run of the whole grid restores these seeds' stage items from the remote",
    ),
    remote_option: Optional[list[str]] = typer.Option(
        None,
        "--remote-option",
        help="KEY=VALUE setting of the DVC remote besides its URL, repeatable; e.g. for an "
        "S3-compatible server: endpointurl=http://host:9000 (credentials: access_key_id, secret_access_key, or the "
        "usual AWS_* environment on every node). Written to each workspace's .dvc/config.local, never to git",
    ),
) -> None:
    """Run a grid (envs x override sets, each with its seeds and dvc.yaml's variants) on Ray.

    One workspace per grid cell (a clone of HEAD with the cell's params.yaml) and one Ray task
    per DVC stage item, ordered by DVC's DAG. Each task runs `dvc repro --single-item --pull`
    in its own clone and pushes outputs and run-cache to --remote; the driver then writes each
    cell's dvc.lock once, restoring every stage from the run-cache. Run it again to resume:
    completed stages are restored, not recomputed, and a completed cell runs nothing.
    """
    options = {}
    for item in remote_option or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            typer.echo(f"error: --remote-option {item!r}: expected KEY=VALUE", err=True)
            raise typer.Exit(code=2)
        options[key.strip()] = value.strip()
    try:
        settings = SweepSettings(
            remote,
            repo=repo,
            workdir=workdir,
            address=address,
            workers=workers,
            max_retries=max_retries,
            git_url=git_url,
            scratch=scratch,
            dry_run=dry_run,
            remote_options=options,
            resume_root=resume_root,
            seeds=seed,
        )
        results = run_sweep(grid, settings, log=typer.echo)
    except SweepError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(code=exc.exit_code) from None
    for r in results:
        typer.echo(f"{r.name}: {r.status} ({len(r.executed)} ran, {len(r.restored)} restored) {r.workspace}")
