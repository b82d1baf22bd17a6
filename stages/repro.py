"""`mapex repro`: `dvc repro` with independent stage items side by side on this machine.

Not a DVC stage: it drives DVC (pipeline/distributed/local.py says how, and why it is safe).
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path
from typing import Optional

import typer

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


@reports_errors
def repro(
    targets: Optional[list[str]] = typer.Argument(
        None, help="stages or stage items to reproduce with everything upstream of them (default: the whole dvc.yaml)"
    ),
    jobs: int = typer.Option(
        0,
        "--jobs",
        "-j",
        min=0,
        help="stage items at most side by side (default 0: one per core of this machine, at most 8); 1 is plain `dvc repro`",
    ),
    root: Path = typer.Option(Path("."), "--root", help="the DVC workspace (the repository root)"),
) -> None:
    """`dvc repro`, with independent stage items side by side.

    Each stage item runs as `dvc repro --single-item ITEM` once every item upstream of it has
    finished, at most --jobs at a time: on 2 cores the two seeds' extractions, evaluations and
    scores run together instead of one after another. DVC decides for each item, as in `dvc
    repro`, whether it reruns, is restored from the run-cache or is skipped as unchanged, and the
    outputs are the same bytes (every stage is a pure command; one torch thread a process).
    Items' output goes to .dvc/tmp/mapex-repro/ITEM.log; a line here as each starts and ends, the
    end of a failed item's log, and a table of every item's wall time at the end. After a failure
    nothing new starts; Ctrl-C (or SIGTERM) reaches the running items, which stop as under
    `dvc repro` (nothing half-written); it exits 130 (143).
    """
    jobs = jobs or min(_cores(), MAX_DEFAULT_JOBS)
    if not (root / "dvc.yaml").is_file():
        raise FileNotFoundError(f"{root / 'dvc.yaml'}: no dvc.yaml here (--root names the DVC workspace)")
    if jobs == 1:
        rc = subprocess.call([_dvc_bin(), "repro", *(targets or [])], cwd=root)
        raise typer.Exit(code=rc)
    try:
        items = stage_items(root, list(targets) if targets else None)
    except (ValueError, LookupError) as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(code=2) from None
    typer.echo(f"{len(items)} stage items, at most {jobs} side by side (logs: .dvc/tmp/mapex-repro/)", err=True)
    try:
        result = repro_parallel(root, items, jobs, echo=lambda line: typer.echo(line, err=True))
    except KeyboardInterrupt:
        typer.echo("stopped: the running stage items were interrupted; rerun to go on", err=True)
        raise typer.Exit(code=130) from None
    except Terminated:
        typer.echo("stopped by SIGTERM: it reached the running stage items; rerun to go on", err=True)
        raise typer.Exit(code=143) from None
    typer.echo(summary_table(result), err=True)
    if result.failed:
        names = ", ".join(r.name for r in result.failed)
        left = f"; not started: {', '.join(result.not_started)}" if result.not_started else ""
        typer.echo(f"error: {names} failed{left}", err=True)
        raise typer.Exit(code=1)
