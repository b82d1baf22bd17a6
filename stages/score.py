"""Stage score: the front and its metrics from re-evaluated returns. Arithmetic only, no episode.

Outputs (in OUT):
  front.csv        the non-dominated members (re-evaluated means), sorted by obj0: id, origin,
                   iteration, obj<m>.
  metrics.json     front and specialist-only metrics (pipeline.evaluation.metrics; "specialists" = every
                   starting policy, all of each specialist's policy set), their HV ratio, the
                   extraction-time hypervolume, and the run's context, with the number of
                   starting policies and of children (DVC metrics); for an extraction that ran
                   one of the extensions, what it recorded (EXTENSION_META).
  hypervolume.csv  one row per extraction iteration t, for the population of every member made
                   by iteration t: iteration, population, env_samples (cumulative, extraction),
                   hypervolume_extract (of the extraction-time returns, the paper's learning
                   curve) and hypervolume (of the same members' re-evaluated returns).
What produced the run (pipeline.core.provenance) goes to the --provenance file, outside OUT; the
report reads it beside those of extract and evaluate.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from pipeline.core.artifacts import ArtifactError, csv_text, read_json, write_text_atomic
from pipeline.core.pareto import pareto_mask
from pipeline.core.population import Member, load_population
from pipeline.core.provenance import write_provenance
from pipeline.evaluation.evaluated import EVALUATION_KEYS, META_KEYS, check_same_run, read_evaluated
from pipeline.evaluation.metrics import hypervolume_history, population_summary
from pipeline.evaluation.reference_points import TABLE, resolve_reference_point
from pipeline.params.score import ScoreParams
from stages.common import PARAMS_OPTION, PROVENANCE_OPTION, read_params, reports_errors

# What population.pt's meta says of extraction's extensions (pipeline.extraction.run.ExtractionRun.record)
EXTENSION_META = ("stopped_at", "init_fallbacks", "seed_interpolation")

# read_evaluated, check_same_run, META_KEYS and EVALUATION_KEYS: pipeline.evaluation.evaluated (export reads them too)


@reports_errors
def score(
    population: Path = typer.Option(..., help="population.pt of a method (extract, mopderl or morld stage)"),
    evaluated: Path = typer.Option(..., help="the evaluate stage's output directory (evaluated.csv, evaluation.json)"),
    out: Path = typer.Option(..., help="output directory (front.csv, metrics.json, hypervolume.csv)"),
    reference_points: Path = typer.Option(
        TABLE, help="the per-env facts file whose `reference_point` is read when env.reference_point is null"
    ),
    params: Path = PARAMS_OPTION,
    provenance: Optional[Path] = PROVENANCE_OPTION,
) -> None:
    """Score the re-evaluated population of one run: its front, metrics and hypervolume history.

    Params: env.reference_point and section `score` (distinct_tol, utility_weights). Where
    env.reference_point is null (the default), the point is the population's env's entry in
    REFERENCE_POINTS (presets/envs.yaml, `reference_point`); an env without one is a one-line error.
    metrics.json records the point and where it came from (reference_point_source). Reads
    POPULATION (members' origin, iteration, extraction-time returns, env samples) and the
    evaluate stage's EVALUATED/evaluated.csv and evaluation.json, which must describe that
    population. The front is the non-dominated set of the re-evaluated mean returns; it is
    scored (hypervolume against env.reference_point, HV fraction of the [reference, ideal] box,
    the paper's sparsity and PGMORL's, expected utility, cardinality, distinct count), and so
    are the specialists alone (every starting policy of their policy sets). The hypervolume
    history is computed for every iteration, on extraction-time and on re-evaluated returns.

    Writes to OUT: front.csv, metrics.json (DVC metrics) and hypervolume.csv (a `dvc plots`
    curve); with --provenance, what produced the run (pipeline.core.provenance) to that file.
    """
    _, env_p, cfg, _ = read_params(params, "score", ScoreParams)
    members, meta = load_population(population, META_KEYS)
    if not members:
        raise ArtifactError(f"{population}: population has no members")
    record = read_json(evaluated / "evaluation.json", EVALUATION_KEYS)
    means = read_evaluated(evaluated / "evaluated.csv", members, meta["n_objectives"])
    check_same_run(evaluated / "evaluation.json", record, population, meta, len(members))
    # auto: from the run's starting policies (MORL/D has none: its whole population)
    starting = means[[m.origin == "specialist" for m in members]]
    resolved = resolve_reference_point(
        env_p.reference_point, meta["env_id"], meta["n_objectives"], params, reference_points,
        starting if len(starting) else means,
    )  # fmt: skip
    ref = resolved.point

    iteration = np.array([m.iteration for m in members])
    extract_returns = np.array([m.returns for m in members], dtype=float)
    summary = population_summary(
        means, np.array([m.origin == "specialist" for m in members]), ref, cfg.distinct_tol, cfg.utility_weights
    )
    history = hypervolume_history(
        iteration,
        np.array([m.env_samples for m in members]),
        {"hypervolume_extract": extract_returns, "hypervolume": means},
        ref,
    )
    metrics = {
        "env_id": meta["env_id"],
        "method": meta["method"],
        "seed": meta["seed"],
        "episodes": record["episodes"],
        "population": len(members),
        "starting_policies": sum(m.origin == "specialist" for m in members),
        # every member the method made: MAPEX's children, MOPDERL's offspring, MORL/D's policies
        "children": sum(m.origin != "specialist" for m in members),
        "iterations": int(iteration.max()),
        "env_samples_extraction": max(m.env_samples for m in members),
        "env_samples_evaluation": record["env_samples_evaluation"],
        # imported specialists: env frames spent collecting their buffers (stage import_specialist)
        "env_samples_collection": int(meta.get("collection_frames", 0)),
        # env frames of the specialists' training (0 for MORL/D; absent where not known: imported ones)
        **(
            {"env_samples_specialists": int(meta["specialist_frames"])}
            if meta.get("specialist_frames") is not None
            else {}
        ),
        # imported slots beside slots trained here (stage train_specialist_imported): where each came from
        **({"specialist_sources": meta["specialist_sources"]} if "specialist_sources" in meta else {}),
        # the extensions of extraction that ran (not in the paper; absent from a paper run's metrics):
        # the early stop (stopped_at: an iteration or null), init interpolate's fallbacks, the seeds
        **{k: meta[k] for k in EXTENSION_META if k in meta},
        **summary,
        "extraction_hypervolume": float(history["hypervolume_extract"][-1]),
        "reference_point": ref.tolist(),
        "reference_point_source": resolved.source,
        "distinct_tol": cfg.distinct_tol,
        "utility_weights": cfg.utility_weights,
    }
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "front.csv", front_csv(members, means))
    write_text_atomic(out / "metrics.json", json.dumps(finite(metrics), indent=2) + "\n")
    write_text_atomic(
        out / "hypervolume.csv", csv_text(list(history), list(zip(*(c.tolist() for c in history.values()))))
    )
    write_provenance(provenance, "score", "cpu")


def finite(obj):
    """JSON-safe copy: NaN and infinities become null (json would write invalid `NaN`)."""
    if isinstance(obj, dict):
        return {k: finite(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [finite(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def front_csv(members: list[Member], means: np.ndarray) -> str:
    """The non-dominated members sorted by obj0 (ties by the later objectives, then id):
    id, origin, iteration, obj<m>. Members with identical returns all appear."""
    ids = sorted(np.flatnonzero(pareto_mask(means)), key=lambda i: (*means[i], i))
    header = ["id", "origin", "iteration", *(f"obj{m}" for m in range(means.shape[1]))]
    return csv_text(header, [[int(i), members[i].origin, members[i].iteration, *map(float, means[i])] for i in ids])
