"""The experiment report: report.md from evaluated runs, assembled from the verdicts, tables
and figure captions of the modules beside it (runs, figures, tables, verdicts, specialists). No file paths here.

A `Run` is one (method, seed): the evaluate stage's re-evaluated returns plus the score
stage's metrics, front, hypervolume history and provenance. A method is an extraction variant
from one kind of specialists (mapex_pderl = the paper's MAPEX, mapex_posthoc_pderl =
MAPEX-PostHoc, mapex_td3 = MAPEX-TD3, warmup_only_<kind> = the ablation) or a baseline
(mopderl, morld, and interpolate_<kind>, weight-space interpolation between the specialists,
which the paper does not have); every method's population is scored by the same evaluator. Figures are matplotlib `Figure`s
rendered with Agg (no pyplot, no global backend state); tables and the verdict are markdown
strings computed from the numbers. Mean +- SEM across seeds as in the paper's Table 1.
"""

from __future__ import annotations

from pipeline.reporting.cost import cost_table, verdict_cost_table
from pipeline.reporting.presentation import label
from pipeline.reporting.runs import Run, methods_in
from pipeline.reporting.specialists import own_returns_table, weak_sentence, weak_specialists
from pipeline.reporting.tables import details_table, paper_table, provenance_table, sample_efficiency_table
from pipeline.reporting.verdicts import verdicts


def report_markdown(
    runs: list[Run],
    env_id: str,
    names: list[str],
    figures: dict[str, str],
    context: dict[str, str],
    min_difference: float = 0.05,
    noise_sems: float = 2.0,
    weak_fraction: float | None = 0.5,
    weak_min_return: list[float | None] | None = None,
    specialist_costs: dict[tuple[str, int], float] | None = None,
    pairs: list[list[str]] | None = None,
) -> str:
    """The whole report.md: weak-specialist warnings and verdicts (and what each side cost),
    tables, what each front cost (`specialist_costs`: (kind, seed) -> the specialists'
    core-seconds, pipeline.reporting.cost.read_specialist_costs), figures (name -> caption, files
    beside report.md), provenance, definitions."""
    seeds = sorted({r.seed for r in runs})
    ref = runs[0].metrics.get("reference_point")
    # where the score stage took it from: env.reference_point, or the env's entry in the table
    sources = sorted({str(r.metrics["reference_point_source"]) for r in runs if "reference_point_source" in r.metrics})
    said = verdicts(runs, min_difference, noise_sems, pairs)
    weak = weak_specialists(runs, weak_fraction, weak_min_return)
    own = own_returns_table(runs, names, weak)
    lines = [
        f"# MAPEX report: {env_id}",
        "",
        f"- methods: {', '.join(f'{label(v)} ({v})' for v in methods_in(runs))}",
        f"- seeds: {', '.join(map(str, seeds))}",
        f"- objectives: {', '.join(f'{i}: {n}' for i, n in enumerate(names))}",
        *(
            [
                "- hypervolume reference points: derived per run from its own starting policies "
                "(env.reference_point: auto; docs/reference_points.md), "
                + "; ".join(f"{label(r.method)} seed {r.seed}: {r.metrics['reference_point']}" for r in runs)
                + ". **Warning:** such hypervolumes compare only within runs that share a point: a verdict or a "
                "mean across runs whose points differ mixes measures; set env.reference_point to one list to compare them",
            ]
            if len({tuple(r.metrics["reference_point"]) for r in runs}) > 1
            else [f"- hypervolume reference point: {ref}" + (f" (from {'; '.join(sources)})" if sources else "")]
        ),
        *(f"- {k}: {v}" for k, v in context.items()),
        "",
        "## Verdicts",
        "",
        *(f"- {weak_sentence(w, names)}" for w in weak),
        *(
            [f"- {v.sentence}" for v in said]
            or [
                "- No pair of comparable methods was run (report.pairs; default: pipeline/reporting/verdicts.py VERDICT_PAIRS)."
            ]
        ),
        "",
        *(
            [
                "Each verdict beside what each side cost: the core-seconds of the stage that made each method's "
                "front (mean over its seeds; its evaluation episodes included, the specialists not: they are "
                "shared; 'What each front cost' below).",
                "",
                vc,
            ]
            if (vc := verdict_cost_table(said, runs))
            else []
        ),
        *(
            [
                "## Specialists on their own objectives",
                "",
                "Each specialist's re-evaluated mean return on the objective it was trained for, per seed and "
                "kind of specialists (every method of that seed and kind starts from the same ones); for a PDERL "
                "policy set, its best policy on that objective ('best of N policies'). '(weak)': below "
                "report.weak_specialist_fraction of its kind's best seed (where that best is <= 0: that fraction "
                "of the way up from the worst return of any starting policy) or below "
                "report.weak_specialist_min_return; a front extracted from it is not evidence about the method.",
                "",
                own,
            ]
            if own
            else []
        ),
        "## Metrics of the re-evaluated final fronts",
        "",
        f"Mean ± SEM across seeds{' (one seed: no SEM)' if len(seeds) < 2 else ''}. The layout of the paper's "
        "Table 1 (one row per environment, a column group per metric); the paper reports hypervolume and "
        "sparsity only, expected utility and distinct points are added here. 'specialists only' is the front "
        "of the specialists alone: every starting policy (all of each specialist's policy set, one policy for a "
        "TD3 specialist), before any child. 'starting policies' and 'made by the method' count the population's "
        "members (MAPEX: its children; MOPDERL: the phase-2 individuals that entered its archive; MORL/D: its policies; "
        "interpolation, a baseline the paper does not have: its policies mixed from the specialists' weights).",
        "",
        paper_table(runs, env_id),
        details_table(runs),
        *(
            [
                "## Sample efficiency: extraction vs distillation from the same specialists",
                "",
                "Cumulative env frames after the specialists (MAPEX and interpolation: their evaluation episodes; MOPDERL: every "
                "phase-2 frame) until a method's population first reaches a fraction of the other's final "
                "re-evaluated hypervolume, on the re-evaluated hypervolume history.",
                "",
                eff,
            ]
            if (eff := sample_efficiency_table(runs))
            else []
        ),
        *(
            [
                "## What each front cost",
                "",
                "Core-seconds (CPU seconds of every thread; a GPU's own time is not in them) of the stage that made "
                "each method's population, mean ± SEM over seeds: for extraction and interpolation the sum of their "
                "per-iteration records (training and evaluating every member, the starting policies' evaluation and "
                "the hybrid extraction's interpolated seeds, on their own line, included; kept across a resume), for "
                "the other methods the stage process's (a resumed run: its last process only). Loading the inputs "
                "is in 'wall s' but in no per-iteration record. 'core-s re-evaluating': the evaluate stage's, which "
                "every method pays per member. The specialists are costed once per seed and kind, apart: every "
                "method of that kind starts from them. From the records under data/provenance; 'n/a' where a stage "
                "recorded none (run by hand without --provenance, or before costs were recorded).",
                "",
                ct,
            ]
            if (ct := cost_table(runs, specialist_costs or {}))
            else []
        ),
        "## Figures",
        "",
    ]
    for fname, caption in figures.items():
        lines += [f"![{caption}]({fname})", "", f"*{caption}*", ""]
    lines += [
        "## Provenance",
        "",
        "What produced each run: the population (extract, or the baseline's own stage), its "
        "re-evaluation (evaluate) and the scoring (score), from the records each stage wrote beside "
        "its outputs (data/provenance; 'not recorded' where a stage wrote none). Runs with identical "
        "provenance share a row. Results are bitwise reproducible only between runs that agree on "
        "every column (README, Reproducibility).",
        "",
        provenance_table(runs),
        "## Definitions",
        "",
        "- Every member of the final population was re-evaluated on fresh episode seeds (not those "
        "used during extraction); the front is the non-dominated set of the re-evaluated mean returns.",
        "- Hypervolume: exact (pymoo) above the fixed reference point. HV fraction: hypervolume over "
        "the volume of the box between the reference point and the ideal point (per-objective maximum "
        "of the re-evaluated population), the same box for the front and for the specialists.",
        "- Sparsity (the paper's Table 1): mean Euclidean distance between neighbouring points of the "
        "front sorted along objective 0. Raw return units. Sparsity (PGMORL): sort the front along each "
        "objective separately, sum the squared neighbour gaps over the objectives, divide by n - 1; "
        "squared units, not comparable with the paper's.",
        "- Expected utility: mean over evenly spread weight vectors w of max over the front of w · J, on "
        "raw (unnormalised) returns as morl-baselines does; the larger-scale objective weighs more.",
        *(
            [
                f"- With {len(names)} objectives the front is a surface, not a curve: the paper's sparsity is "
                "then the mean Euclidean length of the edges of a triangulation of the front (docs/n_objectives.md; "
                "for 2 objectives it is the definition above). Expected utility's weight vectors are then a "
                "Das-Dennis lattice on the simplex, the coarsest with at least score.utility_weights of them."
            ]
            if len(names) >= 3
            else []
        ),
        "- Distinct points: non-dominated points left after merging points closer than the tolerance "
        "(a fraction of the [reference, ideal] box side, objectives normalised to it).",
        "- Extraction-time HV: hypervolume of the front of the returns measured during extraction "
        "(fewer episodes, each member evaluated once); above the re-evaluated HV it shows selection optimism.",
        "- Hypervolume history: after each iteration, the hypervolume of every member made so far, on "
        "extraction-time returns (what the paper plots) and on the same members' re-evaluated returns.",
        "- Core-seconds: CPU seconds (user + system) of every thread of a stage's process and of the worker "
        "processes it waited for (pipeline/core/cost.py); on a CPU, the compute a run took whatever its "
        "thread count.",
        "",
    ]
    return "\n".join(lines)
