"""`mapex grid-report`: one report across the cells of a sweep (docs/sweeps.md).

Not a DVC stage: it reads the workspaces `mapex repro --ray` leaves behind (one per grid cell, each
with its params.yaml and its restored data/score, data/evaluate and data/provenance) and writes
one folder.
"""

from __future__ import annotations

import re
from pathlib import Path

import typer

from pipeline.core.artifacts import ArtifactError, atomic_path
from pipeline.core.envs import objective_names
from pipeline.params import EnvParams, ParamsError, RunParams, load_params, section
from pipeline.params.report import ReportParams
from pipeline.reporting.grid import Cell, Side, cross_lines, grid_fronts_figure, grid_history_figure, grid_markdown
from pipeline.reporting.runs import check_comparable, load_runs, methods_in
from stages.common import check_min_return, reports_errors


def load_cell(ws: Path) -> Cell:
    """One cell workspace: its params (env, seeds, methods, report) and the runs scored there."""
    raw = load_params(ws / "params.yaml")
    env_p, run_p = section(raw, "env", EnvParams, ws / "params.yaml"), section(raw, "", RunParams, ws / "params.yaml")
    report_p = section(raw, "report", ReportParams, ws / "params.yaml")
    runs = [
        r
        for r in load_runs(ws / "data" / "score", ws / "data" / "evaluate", ws / "data" / "provenance")
        if r.seed in run_p.seeds and r.method in run_p.methods
    ]
    if not runs:
        raise ArtifactError(
            f"{ws / 'data' / 'score'}: no scored run for seeds {run_p.seeds} and methods {run_p.methods}"
        )
    check_comparable(ws / "data" / "score", runs, env_p.id)
    names = objective_names(env_p.id, runs[0].returns.shape[1], env_p.objective_names)
    check_min_return(report_p.weak_specialist_min_return, len(names), ws / "params.yaml")
    return Cell(ws.name, env_p.id, runs, names, report_p)


def parse_pairs(values: list[str], cells: list[Cell], workdir: Path, skipped: list[str]) -> list[tuple[Side, Side]]:
    """The --pair values ('CELL_A/METHOD_A,CELL_B/METHOD_B' each) as sides of WORKDIR's scored
    cells; a one-line error naming the value and the cell or method that is not there (and what
    is), or the report params the two cells disagree on."""
    by_name = {c.name: c for c in cells}
    pairs = []
    for value in values:
        parts = [p for p in re.split(r"[,\s]+", value.strip()) if p]
        if len(parts) != 2 or any(not c or not m for c, _, m in (p.partition("/") for p in parts)):
            raise ParamsError(f"--pair {value!r}: expected CELL_A/METHOD_A,CELL_B/METHOD_B")
        sides = []
        for part in parts:
            cell, _, method = part.partition("/")
            if cell not in by_name:
                why = "is not scored (no data/score)" if cell in skipped else "is not a cell"
                raise ArtifactError(
                    f"--pair {value!r}: {cell!r} {why} in {workdir} (scored cells: {', '.join(by_name)})"
                )
            present = methods_in(by_name[cell].runs)
            if method not in present:
                raise ArtifactError(
                    f"--pair {value!r}: cell {cell} of {workdir} has no scored run of method {method!r} "
                    f"(its methods: {', '.join(present)})"
                )
            sides.append(Side(by_name[cell], method))
        a, b = sides
        if (a.cell.name, a.method) == (b.cell.name, b.method):
            raise ParamsError(f"--pair {value!r}: compares {a.method} of cell {a.cell.name} with itself")
        for key in ("min_difference", "noise_sems"):
            va, vb = getattr(a.cell.report, key), getattr(b.cell.report, key)
            if va != vb:
                raise ParamsError(
                    f"--pair {value!r}: cells {a.cell.name} and {b.cell.name} have different report.{key} "
                    f"({va:g} and {vb:g} in their params.yaml); a verdict across them needs one rule"
                )
        pairs.append((a, b))
    return pairs


@reports_errors
def grid_report(
    workdir: Path = typer.Argument(
        ...,
        help="a sweep's work directory: one workspace per grid cell (default of "
        "`mapex repro --ray`: sweeps/<grid file name>)",
    ),
    out: Path = typer.Option(..., help="report folder to write (replaced as a whole)"),
    width: float = typer.Option(13.0, min=4, help="figure width in inches"),
    dpi: int = typer.Option(110, min=30, help="figure resolution"),
    pair: list[str] | None = typer.Option(
        None,
        "--pair",
        metavar="CELL_A/METHOD_A,CELL_B/METHOD_B",
        help="a paired verdict, by seed, of METHOD_A in cell CELL_A against METHOD_B in cell CELL_B, by the "
        "per-cell report's rule and words (repeatable)",
    ),
) -> None:
    """Write one report across a sweep's grid: Table 1 with a row per cell (env), fronts and
    hypervolume-vs-frames per cell, each cell's weak specialists (by its own `report` params)
    and the provenance of every cell's runs; with --pair, paired verdicts across cells.

    Reads every WORKDIR/<cell>/ holding a params.yaml and a data/score folder (cells without
    scores, e.g. a sweep run only up to some targets, are listed and skipped). Writes OUT/report.md,
    OUT/fronts.png and OUT/hypervolume.png; the folder is built beside OUT and renamed into place.

    Each --pair CELL_A/METHOD_A,CELL_B/METHOD_B (a quoted space instead of the comma works too)
    adds the verdict the per-cell report writes for a pair of its report.pairs (same function,
    rule, wording and cost column; the cells' report.min_difference and report.noise_sems must
    agree), here of a method of one cell against a method of another, paired by seed over the
    seeds both have; the seeds only one side has are named as left out.
    """
    if not workdir.is_dir():
        raise ArtifactError(f"{workdir}: not a directory (expected a sweep's work directory)")
    spaces = sorted(d for d in workdir.iterdir() if (d / "params.yaml").is_file())
    scored = [d for d in spaces if (d / "data" / "score").is_dir()]
    for d in sorted(set(spaces) - set(scored)):
        typer.echo(f"skipped {d.name}: no data/score (the sweep did not score this cell)", err=True)
    if not scored:
        raise ArtifactError(f"{workdir}: no cell workspace with params.yaml and data/score")
    cells = [load_cell(d) for d in scored]
    across = cross_lines(parse_pairs(pair or [], cells, workdir, [d.name for d in spaces if d not in scored]))
    figures = {"fronts": grid_fronts_figure(cells, width), "hypervolume": grid_history_figure(cells, width)}
    captions = {
        "fronts.png": "Re-evaluated fronts of every method, one panel per cell, one line per seed.",
        "hypervolume.png": "Re-evaluated hypervolume against cumulative env frames after the specialists "
        "(mean ± SEM over seeds), one panel per cell.",
    }
    text = grid_markdown(cells, captions, across)
    if out.is_dir() and any(out.iterdir()) and not (out / "report.md").is_file():
        raise ArtifactError(f"{out}: exists and is not a report folder; refusing to replace it")
    with atomic_path(out) as tmp:
        tmp.mkdir()
        for name, fig in figures.items():
            fig.savefig(tmp / f"{name}.png", dpi=dpi)
        (tmp / "report.md").write_text(text)
    typer.echo(f"grid report of {len(cells)} cell(s): {out / 'report.md'}")
