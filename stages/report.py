"""Stage report: one self-contained folder (report.md + figures) from every evaluated run."""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import numpy as np
import typer

from pipeline.artifacts import ArtifactError, atomic_path
from pipeline.envs import objective_names
from pipeline.params import RunParams, section
from pipeline.params.report import ReportParams
from pipeline.report import Run, front_figure, history_figure, label, report_markdown, variants_in
from stages.common import PARAMS_OPTION, read_params, reports_errors

RUN_DIR = re.compile(r"^seed(\d+)$")


@reports_errors
def report(
    evaluated: Path = typer.Option(..., help="root of the evaluate outputs, scanned for VARIANT/seedS/metrics.json"),
    extracted: Path = typer.Option(..., help="root of the extract outputs, holding VARIANT/seedS/history.csv"),
    out: Path = typer.Option(..., help="report folder to write (replaced as a whole)"),
    params: Path = PARAMS_OPTION,
) -> None:
    """Write the experiment report: fronts, hypervolume curves, the metrics table and the verdict.

    Params: sections `env` (objective names) and `report`. Reads every EVALUATED/VARIANT/seedS
    (metrics.json, evaluated.csv from `evaluate`) and EXTRACTED/VARIANT/seedS/history.csv (from
    `extract`). Writes OUT/report.md with one front figure per seed (front_seedS.png), the
    hypervolume history (hypervolume.png) and a Table-1-shaped metrics table (mean ± SEM across
    seeds). The folder is built beside OUT and renamed into place when complete.
    """
    raw, env_p, cfg = read_params(params, "report", ReportParams)
    seeds = section(raw, "", RunParams, params).seeds
    # Only the seeds params.yaml names: folders of seeds dropped from the list may linger.
    runs = [r for r in load_runs(evaluated, extracted) if r.seed in seeds]
    if not runs:
        raise ArtifactError(f"{evaluated}: no evaluated run for seeds {seeds}")
    if {r.metrics.get("env_id") for r in runs} != {env_p.id}:
        raise ArtifactError(f"{evaluated}: runs are for env(s) {sorted({str(r.metrics.get('env_id')) for r in runs})}, "
                            f"params env.id is {env_p.id!r}")
    names = objective_names(env_p.id, runs[0].returns.shape[1], env_p.objective_names)

    figures: dict[str, object] = {}
    captions: dict[str, str] = {}
    for seed in sorted({r.seed for r in runs}):
        by_variant = {r.variant: r for r in runs if r.seed == seed}
        figures[f"front_seed{seed}"] = front_figure(by_variant, names, env_p.id, seed, cfg.figure_width)
        captions[f"front_seed{seed}.png"] = (f"Seed {seed}: re-evaluated returns of every member; "
                                             f"{' vs '.join(label(v) for v in variants_in(list(by_variant.values())))} side by side.")
    figures["hypervolume"] = history_figure(runs, env_p.id, cfg.figure_width)
    captions["hypervolume.png"] = "Extraction-time hypervolume vs iteration and vs cumulative env samples."
    context = {"evaluation episodes per member": str(runs[0].metrics.get("episodes"))}
    text = report_markdown(runs, env_p.id, names, captions, context, cfg.min_difference)

    if out.is_dir() and any(out.iterdir()) and not (out / "report.md").is_file():
        raise ArtifactError(f"{out}: exists and is not a report folder; refusing to replace it")
    with atomic_path(out) as tmp:
        tmp.mkdir()
        for name, fig in figures.items():
            for fmt in cfg.formats:
                fig.savefig(tmp / f"{name}.{fmt}", dpi=cfg.dpi)
        (tmp / "report.md").write_text(text)


def load_runs(evaluated: Path, extracted: Path) -> list[Run]:
    """Every EVALUATED/VARIANT/seedS with a metrics.json, with its evaluated.csv and history.csv."""
    if not evaluated.is_dir():
        raise ArtifactError(f"{evaluated}: not a directory of evaluate outputs")
    runs = []
    for metrics_path in sorted(evaluated.glob("*/seed*/metrics.json")):
        run_dir = metrics_path.parent
        match = RUN_DIR.match(run_dir.name)
        if match is None:
            continue
        variant, seed = run_dir.parent.name, int(match.group(1))
        metrics = _read_json(metrics_path)
        cols = _read_csv(run_dir / "evaluated.csv", ["origin", "iteration", "on_front", "obj0", "obj1"])
        n_obj = sum(1 for k in cols if re.fullmatch(r"obj\d+", k))
        hist = _read_csv(extracted / variant / run_dir.name / "history.csv", ["iteration", "env_samples", "hypervolume"])
        try:
            runs.append(Run(
                variant=variant, seed=seed, metrics=metrics,
                returns=np.stack([np.asarray(cols[f"obj{m}"], float) for m in range(n_obj)], axis=1),
                origin=np.asarray(cols["origin"]), iteration=np.asarray(cols["iteration"], int),
                on_front=np.asarray(cols["on_front"], int).astype(bool),
                history={k: np.asarray(hist[k], float) for k in ("iteration", "env_samples", "hypervolume")},
            ))
        except ValueError as exc:
            raise ArtifactError(f"{run_dir}: unreadable numbers in evaluated.csv or history.csv ({exc})") from None
    if not runs:
        raise ArtifactError(f"{evaluated}: no VARIANT/seedS/metrics.json found (run the evaluate stage first)")
    return runs


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ArtifactError(f"{path}: cannot be read as JSON ({exc})") from None
    missing = [k for k in ("front", "specialists", "hv_ratio_vs_specialists", "iterations") if k not in data]
    if missing:
        raise ArtifactError(f"{path}: not an evaluate metrics file (missing {missing})")
    return data


def _read_csv(path: Path, required: list[str]) -> dict[str, list[str]]:
    """Columns of a CSV file by name; ArtifactError naming the file if it is missing, empty or lacks a column."""
    if not path.is_file():
        raise ArtifactError(f"{path}: file not found")
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise ArtifactError(f"{path}: no rows")
    missing = [c for c in required if c not in rows[0]]
    if missing:
        raise ArtifactError(f"{path}: missing column(s) {missing}")
    return {k: [r[k] for r in rows] for k in rows[0]}
