"""Stage report: one self-contained folder (report.md + figures) from every scored run."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from pipeline.core.artifacts import ArtifactError, atomic_path
from pipeline.core.envs import objective_names
from pipeline.params import ParamsError
from pipeline.params.report import ReportParams
from pipeline.params.variants import is_hybrid, parse_variants
from pipeline.reporting.cost import method_core_seconds, read_specialist_costs
from pipeline.reporting.figures import (
    barrier_figure,
    cost_figure,
    front_caption,
    front_figure,
    history_figure,
    total_frames_figure,
)
from pipeline.reporting.gallery import gallery_markdown
from pipeline.reporting.presentation import label, use_variants
from pipeline.reporting.report import report_markdown
from pipeline.reporting.runs import Run, check_comparable, load_runs
from pipeline.reporting.specialists import sources_line
from stages.common import PARAMS_OPTION, check_min_return, read_params, reports_errors


@reports_errors
def report(
    evaluated: Path = typer.Option(..., help="root of the evaluate outputs, holding METHOD/seedS/evaluated.csv"),
    scored: Path = typer.Option(..., help="root of the score outputs, scanned for METHOD/seedS/metrics.json"),
    provenance: Optional[Path] = typer.Option(
        None,
        help="root of the stages' provenance records, holding fronts|evaluate|score/METHOD/seedS.json "
        "(default: none; the provenance table then says 'not recorded')",
    ),
    out: Path = typer.Option(..., help="report folder to write (replaced as a whole)"),
    render: Optional[Path] = typer.Option(
        None, help="stage render's folder: the report links its explorer.html and shows thumbnails (default: none)"
    ),
    params: Path = PARAMS_OPTION,
) -> None:
    """Write the experiment report: verdicts, metrics table, fronts, hypervolume curves, provenance.

    Params: sections `env` (id, objective names), `seeds`, `methods` and `report`. Reads every
    SCORED/METHOD/seedS (metrics.json, front.csv, hypervolume.csv from `score`) of the seeds and
    methods params.yaml lists, EVALUATED/METHOD/seedS/evaluated.csv (from `evaluate`) and, under
    PROVENANCE, the records fronts/, evaluate/ and score/METHOD/seedS.json the stages wrote
    (each 'not recorded' in the table where absent). Writes OUT/report.md with a verdict for each pair of comparable methods
    that was run (MAPEX vs its warm-up only ablation, vs MAPEX-TD3, vs MOPDERL and MORL/D:
    beyond the seed noise or tied; report.noise_sems, report.min_difference), a
    warning for each specialist weak on its own objective (report.weak_specialist_fraction,
    report.weak_specialist_min_return), each specialist's return on its own objective, a
    Table-1-shaped metrics table (mean ± SEM across seeds) and a details table (counts of
    starting policies and of the members each method made), the frames MAPEX and MOPDERL need
    to reach each other's hypervolume (when both ran), one front figure per seed
    (front_seedS.png: starting policies apart from the rest; with 3 or more objectives every
    pair of objectives and a 3-D view), the hypervolume history
    (hypervolume.png), what each front cost (core-seconds of the stage that made it, its
    re-evaluation and its specialists, from the provenance records; a cost column beside the
    verdicts; cost.png, hypervolume against cumulative core-seconds, where any cost was
    recorded) and what produced each run (its stages' provenance); with --render, a link
    to stage render's explorer.html and thumbnails of each filmed front's ends and middle
    (thumbs/). The folder is built beside OUT and renamed
    into place when complete.
    """
    raw, env_p, cfg, run_p = read_params(params, "report", ReportParams)
    seeds, methods = run_p.seeds, run_p.methods
    variants = parse_variants(run_p.variants)
    # the variants' labels, colours and pairs, and which methods are hybrids (from the params, not guessed)
    use_variants(variants, {m for m in methods if is_hybrid(raw, m, variants)})
    for i, pair in enumerate(cfg.pairs or []):
        stray = [m for m in pair if m not in methods]
        if stray:
            raise ParamsError(f"{params}: report.pairs[{i}] = {pair}: {stray[0]!r} is not in methods {methods}")
    # Only the seeds and methods params.yaml names: folders of ones dropped from the lists may linger.
    runs = [r for r in load_runs(scored, evaluated, provenance) if r.seed in seeds and r.method in methods]
    if not runs:
        raise ArtifactError(f"{scored}: no scored run for seeds {seeds} and methods {methods}")
    check_comparable(scored, runs, env_p.id)
    names = objective_names(env_p.id, runs[0].returns.shape[1], env_p.objective_names)
    check_min_return(cfg.weak_specialist_min_return, len(names), params)

    figures: dict[str, object] = {}
    captions: dict[str, str] = {}
    for seed in sorted({r.seed for r in runs}):
        by_variant = {r.method: r for r in runs if r.seed == seed}
        figures[f"front_seed{seed}"] = front_figure(by_variant, names, env_p.id, seed, cfg.figure_width)
        captions[f"front_seed{seed}.png"] = front_caption(list(by_variant.values()), seed)
    figures["hypervolume"] = history_figure(runs, env_p.id, cfg.figure_width)
    captions["hypervolume.png"] = (
        "Hypervolume of the population after each iteration (MOPDERL: generation), vs "
        "iteration and vs cumulative env frames after the specialists (MAPEX: its evaluation episodes; MOPDERL: all "
        "of phase 2; MORL/D: all its frames, it has no specialists): returns measured while "
        "the method ran (solid) and the same members re-evaluated (dashed)."
    )
    if (total := total_frames_figure(runs, env_p.id, cfg.figure_width)) is not None:
        figures["total_frames"] = total
        left_out = sorted({label(r.method) for r in runs if "env_samples_specialists" not in r.metrics}, key=str)
        captions["total_frames.png"] = (
            "Re-evaluated hypervolume of the population against total env frames: the specialists' training "
            "(TD3: train_specialist.total_steps each, a shared prefix once; PDERL: its frames per objective; "
            "MORL/D: none) plus the method's own frames, so each curve starts where its specialists' training "
            "ends; mean ± SEM over seeds. The comparison at a fixed sample budget."
            + (f" Not drawn (their specialists' frames are not recorded): {', '.join(left_out)}." if left_out else "")
        )
    first = min(r.seed for r in runs)
    if len(names) == 2 and (barrier := barrier_figure(runs, names, env_p.id, first, cfg.figure_width)) is not None:
        figures["barrier"] = barrier
        captions["barrier.png"] = (
            f"Each objective's re-evaluated return along the interpolation path between seed {first}'s specialists "
            "(mixing weight l from 0 to 1), one line per interpolation method of the run (plain; aligned, repaired "
            "or RegMean where params variants set interpolate.align, repair or mix); the dotted line joins the "
            "specialists' returns: where a method's line sags below it, mixing loses there (the barrier)."
        )
    if any(method_core_seconds(r) is not None for r in runs):
        figures["cost"] = cost_figure(runs, env_p.id, cfg.figure_width)
        captions["cost.png"] = (
            "Re-evaluated hypervolume of the population after each iteration against the cumulative core-seconds "
            "of the stage that made it (log axis; the specialists' not included): a curve (mean ± SEM over seeds) "
            "where the stage recorded per-iteration costs (extraction, interpolation; the hybrid extraction's "
            "interpolated seeds in its first point), one point at the final front where it recorded only its "
            "total; a method with no recorded cost is not drawn."
        )
    context = {
        "evaluation episodes per member": str(runs[0].metrics["episodes"]),
        "starting policies per specialist": starting_policies_line(runs),
    }
    sources = sources_line(runs, names)  # a run from imported specialists and ones trained here
    if sources:
        context["specialists of the imported kind"] = sources
    text = report_markdown(
        runs,
        env_p.id,
        names,
        captions,
        context,
        cfg.min_difference,
        cfg.noise_sems,
        cfg.weak_specialist_fraction,
        cfg.weak_specialist_min_return,
        read_specialist_costs(provenance, runs),
        cfg.pairs,
    )

    if out.is_dir() and any(out.iterdir()) and not (out / "report.md").is_file():
        raise ArtifactError(f"{out}: exists and is not a report folder; refusing to replace it")
    with atomic_path(out) as tmp:
        tmp.mkdir()
        for name, fig in figures.items():
            for fmt in cfg.formats:
                fig.savefig(tmp / f"{name}.{fmt}", dpi=cfg.dpi)
        gallery = gallery_markdown(render, out, tmp, methods, seeds) if render is not None else ""
        if gallery:
            text += "\n" + gallery
        (tmp / "report.md").write_text(text)


def starting_policies_line(runs: list[Run]) -> str:
    """'specialist 0: 3, specialist 1: 3' (the policies of each specialist's policy set that
    started the population), or each run's where they differ."""

    def text(r: Run) -> str:
        return ", ".join(f"specialist {k}: {n}" if k >= 0 else f"{n}" for k, n in r.starting_counts().items()) or "none"

    lines = {text(r) for r in runs}
    if len(lines) == 1:
        return lines.pop()
    return "; ".join(
        f"{label(r.method)} seed {r.seed}: {text(r)}" for r in sorted(runs, key=lambda r: (r.seed, r.method))
    )
