"""Stage report: one self-contained folder (report.md + figures) from every scored run."""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import numpy as np
import typer

from pipeline.core.artifacts import ArtifactError, atomic_path
from pipeline.core.envs import objective_names
from pipeline.params import RunParams, section
from pipeline.params.report import ReportParams
from pipeline.reporting.report import Run, front_figure, history_figure, label, report_markdown, variants_in
from stages.common import PARAMS_OPTION, read_params, reports_errors

RUN_DIR = re.compile(r"^seed(\d+)$")
METRICS_KEYS = ("env_id", "variant", "seed", "episodes", "front", "specialists", "hv_ratio_vs_specialists",
                "extraction_hypervolume", "iterations", "env_samples_extraction", "reference_point")
FRONT_KEYS = ("hypervolume", "hv_fraction", "sparsity", "sparsity_pgmorl", "expected_utility", "cardinality", "distinct_count")
HISTORY_COLUMNS = ("iteration", "env_samples", "hypervolume_extract", "hypervolume")


@reports_errors
def report(
    evaluated: Path = typer.Option(..., help="root of the evaluate outputs, holding METHOD/seedS/evaluated.csv"),
    scored: Path = typer.Option(..., help="root of the score outputs, scanned for METHOD/seedS/metrics.json"),
    out: Path = typer.Option(..., help="report folder to write (replaced as a whole)"),
    params: Path = PARAMS_OPTION,
) -> None:
    """Write the experiment report: verdicts, metrics table, fronts, hypervolume curves, provenance.

    Params: sections `env` (id, objective names), `seeds`, `methods` and `report`. Reads every
    SCORED/METHOD/seedS (metrics.json, front.csv, hypervolume.csv, provenance.json from
    `score`) of the seeds and methods params.yaml lists, and EVALUATED/METHOD/seedS/evaluated.csv
    (from `evaluate`). Writes OUT/report.md with a verdict for each pair of comparable methods
    that was run (MAPEX vs its warm-up only ablation, vs MAPEX-TD3, vs MOPDERL and MORL/D:
    beyond the seed noise or tied; report.noise_sems, report.min_difference), a
    Table-1-shaped metrics table (mean ± SEM across seeds) and a details table (counts of
    starting policies and of the members each method made), the frames MAPEX and MOPDERL need
    to reach each other's hypervolume (when both ran), one front figure per seed
    (front_seedS.png: starting policies apart from the rest), the hypervolume history
    (hypervolume.png) and each run's provenance. The folder is built beside OUT and renamed
    into place when complete.
    """
    raw, env_p, cfg = read_params(params, "report", ReportParams)
    run_p = section(raw, "", RunParams, params)
    seeds, methods = run_p.seeds, run_p.methods
    # Only the seeds and methods params.yaml names: folders of ones dropped from the lists may linger.
    runs = [r for r in load_runs(scored, evaluated) if r.seed in seeds and r.variant in methods]
    if not runs:
        raise ArtifactError(f"{scored}: no scored run for seeds {seeds} and methods {methods}")
    check_comparable(scored, runs, env_p.id)
    names = objective_names(env_p.id, runs[0].returns.shape[1], env_p.objective_names)

    figures: dict[str, object] = {}
    captions: dict[str, str] = {}
    for seed in sorted({r.seed for r in runs}):
        by_variant = {r.variant: r for r in runs if r.seed == seed}
        figures[f"front_seed{seed}"] = front_figure(by_variant, names, env_p.id, seed, cfg.figure_width)
        captions[f"front_seed{seed}.png"] = (f"Seed {seed}: re-evaluated returns of every member, starting policies "
                                             f"as stars (one colour per specialist), what each method made coloured by iteration; "
                                             f"{' vs '.join(label(v) for v in variants_in(list(by_variant.values())))} side by side.")
    figures["hypervolume"] = history_figure(runs, env_p.id, cfg.figure_width)
    captions["hypervolume.png"] = ("Hypervolume of the population after each iteration (MOPDERL: generation), vs "
                                   "iteration and vs cumulative env frames after the specialists (MAPEX: its evaluation episodes; MOPDERL: all "
                                   "of phase 2; MORL/D: all its frames, it has no specialists): returns measured while "
                                   "the method ran (solid) and the same members re-evaluated (dashed).")
    context = {"evaluation episodes per member": str(runs[0].metrics["episodes"]),
               "starting policies per specialist": starting_policies_line(runs)}
    text = report_markdown(runs, env_p.id, names, captions, context, cfg.min_difference, cfg.noise_sems)

    if out.is_dir() and any(out.iterdir()) and not (out / "report.md").is_file():
        raise ArtifactError(f"{out}: exists and is not a report folder; refusing to replace it")
    with atomic_path(out) as tmp:
        tmp.mkdir()
        for name, fig in figures.items():
            for fmt in cfg.formats:
                fig.savefig(tmp / f"{name}.{fmt}", dpi=cfg.dpi)
        (tmp / "report.md").write_text(text)


def starting_policies_line(runs: list[Run]) -> str:
    """'specialist 0: 3, specialist 1: 3' (the policies of each specialist's policy set that
    started the population), or each run's where they differ."""
    def text(r: Run) -> str:
        return ", ".join(f"specialist {k}: {n}" if k >= 0 else f"{n}" for k, n in r.starting_counts().items()) or "none"

    lines = {text(r) for r in runs}
    if len(lines) == 1:
        return lines.pop()
    return "; ".join(f"{label(r.variant)} seed {r.seed}: {text(r)}" for r in sorted(runs, key=lambda r: (r.seed, r.variant)))


def load_runs(scored: Path, evaluated: Path) -> list[Run]:
    """Every SCORED/VARIANT/seedS with a metrics.json, with its score outputs and evaluated.csv."""
    if not scored.is_dir():
        raise ArtifactError(f"{scored}: not a directory of score outputs")
    runs = []
    for metrics_path in sorted(scored.glob("*/seed*/metrics.json")):
        run_dir = metrics_path.parent
        match = RUN_DIR.match(run_dir.name)
        if match is None:
            continue
        runs.append(load_run(run_dir, evaluated / run_dir.parent.name / run_dir.name, run_dir.parent.name, int(match.group(1))))
    if not runs:
        raise ArtifactError(f"{scored}: no VARIANT/seedS/metrics.json found (run the score stage first)")
    return runs


def load_run(score_dir: Path, eval_dir: Path, variant: str, seed: int) -> Run:
    """One run from its score folder and evaluate folder; ArtifactError naming the file on a bad input."""
    metrics = _read_json(score_dir / "metrics.json", METRICS_KEYS)
    for group in ("front", "specialists"):
        missing = [k for k in FRONT_KEYS if k not in (metrics[group] if isinstance(metrics[group], dict) else {})]
        if missing:
            raise ArtifactError(f"{score_dir / 'metrics.json'}: no {', '.join(f'{group}.{k}' for k in missing)} key")
    if (metrics["variant"], metrics["seed"]) != (variant, seed):
        raise ArtifactError(f"{score_dir / 'metrics.json'}: is for variant {metrics['variant']!r} seed {metrics['seed']!r}, "
                            f"but sits in {variant}/seed{seed}")
    chain = _read_json(score_dir / "provenance.json", ())
    members = _read_csv(eval_dir / "evaluated.csv", ["origin", "iteration", "obj0", "obj1"])
    n_obj = sum(1 for k in members if re.fullmatch(r"obj\d+", k))
    front = _read_csv(score_dir / "front.csv", ["id"], allow_empty=True)
    hist = _read_csv(score_dir / "hypervolume.csv", list(HISTORY_COLUMNS))
    try:
        ids = np.asarray(front.get("id", []), int)
        on_front = np.zeros(len(members["origin"]), bool)
        on_front[ids] = True
        return Run(
            variant=variant, seed=seed, metrics=metrics,
            returns=np.stack([np.asarray(members[f"obj{m}"], float) for m in range(n_obj)], axis=1),
            origin=np.asarray(members["origin"]), iteration=np.asarray(members["iteration"], int), on_front=on_front,
            history={k: np.asarray(hist[k], float) for k in HISTORY_COLUMNS}, provenance=chain,
            objective=np.array([int(x) if x != "" else -1 for x in members.get("objective", [""] * len(members["origin"]))]),
        )
    except (ValueError, IndexError) as exc:
        raise ArtifactError(f"{score_dir}: front.csv, hypervolume.csv or {eval_dir / 'evaluated.csv'} "
                            f"do not fit together or hold unreadable numbers ({exc})") from None


def check_comparable(scored: Path, runs: list[Run], env_id: str) -> None:
    """Every run is for params env.id and was scored against one reference point."""
    envs = sorted({str(r.metrics["env_id"]) for r in runs})
    if envs != [env_id]:
        raise ArtifactError(f"{scored}: runs are for env(s) {envs}, params env.id is {env_id!r}")
    refs = {tuple(r.metrics["reference_point"]) for r in runs}
    if len(refs) > 1:
        raise ArtifactError(f"{scored}: runs were scored against different reference points {sorted(refs)}; rerun score")


def _read_json(path: Path, keys: tuple[str, ...]) -> dict:
    if not path.is_file():
        raise ArtifactError(f"{path}: file not found")
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ArtifactError(f"{path}: cannot be read as JSON ({exc})") from None
    if not isinstance(data, dict):
        raise ArtifactError(f"{path}: expected a JSON object, got {type(data).__name__}")
    missing = [k for k in keys if k not in data]
    if missing:
        raise ArtifactError(f"{path}: no {', '.join(map(repr, missing))} key")
    return data


def _read_csv(path: Path, required: list[str], allow_empty: bool = False) -> dict[str, list[str]]:
    """Columns of a CSV file by name; ArtifactError naming the file if it is missing, empty or lacks a column."""
    if not path.is_file():
        raise ArtifactError(f"{path}: file not found")
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        rows = list(reader)
        header = reader.fieldnames or []
    if not rows and not allow_empty:
        raise ArtifactError(f"{path}: no rows")
    missing = [c for c in required if c not in header]
    if missing:
        raise ArtifactError(f"{path}: missing column(s) {missing}")
    return {k: [r[k] for r in rows] for k in header}
