"""Stage evaluate: re-evaluate every member of a final population on fresh episodes, score the front.

Outputs (in OUT):
  evaluated.csv  one row per member: id, origin, objective, iteration, parents (';'-joined),
                 env_samples, obj<m>_extract (extraction-time mean return), obj<m> and obj<m>_std
                 (re-evaluated mean and std over `evaluate.episodes` episodes), on_front (0/1:
                 non-dominated among the re-evaluated means). Columns are named obj0, obj1, ...
                 rather than after the objectives so dvc.yaml's plot axes fit every env.
  front.csv      the non-dominated members, sorted by obj0: id, origin, iteration, obj<m>.
  metrics.json   front and specialist-only metrics (pipeline.metrics), their HV ratio, context.
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import numpy as np
import typer

from pipeline.artifacts import ArtifactError, write_text_atomic
from pipeline.envs import env_spec, make_env
from pipeline.evaluation import eval_seeds, evaluate_policy
from pipeline.metrics import hypervolume, non_dominated, population_summary
from pipeline.pareto import pareto_mask
from pipeline.params import ParamsError
from pipeline.params.evaluate import EvaluateParams
from pipeline.population import load_population, member_actor
from pipeline.seeding import select_device
from stages.common import PARAMS_OPTION, fmt_vec, progress, read_params, reports_errors


@reports_errors
def evaluate(
    population: Path = typer.Option(..., help="population.pt written by the extract stage"),
    out: Path = typer.Option(..., help="output directory (evaluated.csv, front.csv, metrics.json)"),
    seed: int = typer.Option(0, help="run seed of the population (must match its metadata)"),
    params: Path = PARAMS_OPTION,
) -> None:
    """Re-evaluate every member of an extracted population on fresh episode seeds and score the front.

    Params: sections `env` (id, max_episode_steps, reference_point) and `evaluate`. Each member
    runs `evaluate.episodes` deterministic episodes whose seeds differ from extraction's. The
    non-dominated set of the re-evaluated mean returns is scored (hypervolume against
    env.reference_point, HV fraction of the [reference, ideal] box, sparsity, expected utility,
    cardinality, distinct count), and so are the specialists alone.

    Writes to OUT: evaluated.csv (one row per member; a `dvc plots` scatter of obj0 vs obj1),
    front.csv and metrics.json.
    """
    _, env_p, cfg = read_params(params, "evaluate", EvaluateParams)
    members, meta = load_population(population)
    ref = _reference_point(env_p.reference_point, meta["n_objectives"], params)
    _check_population(population, members, meta, env_p.id, seed)
    try:
        device = select_device(cfg.device)
    except ValueError as exc:
        raise ParamsError(f"{params}: evaluate.device: {exc}") from None
    envs = [make_env(env_p.id, env_p.max_episode_steps) for _ in range(cfg.episodes)]
    spec = env_spec(envs[0], env_p.id, env_p.max_episode_steps)
    if (spec.obs_dim, spec.act_dim, spec.n_objectives) != (meta["obs_dim"], meta["act_dim"], meta["n_objectives"]):
        raise ArtifactError(f"{population}: dims (obs, act, objectives) {(meta['obs_dim'], meta['act_dim'], meta['n_objectives'])} "
                            f"do not match env {env_p.id} {(spec.obs_dim, spec.act_dim, spec.n_objectives)}")

    results = []
    with progress(len(members), f"evaluate {meta.get('variant', '?')} seed {seed}", unit="policy") as bar:
        for i, member in enumerate(members):
            res = evaluate_policy(member_actor(member, meta).to(device), envs, eval_seeds(seed, cfg.seed_stream, i, cfg.episodes))
            results.append(res)
            bar.set_postfix_str(f"{member.origin} {i} return {fmt_vec(res.mean)}", refresh=False)
            bar.update(1)
    for env in envs:
        env.close()

    means = np.stack([r.mean for r in results])
    on_front = pareto_mask(means)
    summary = population_summary(means, np.array([m.origin == "specialist" for m in members]), ref, cfg.distinct_tol, cfg.utility_weights)
    extract_returns = np.array([m.returns for m in members], dtype=float)
    metrics = {
        "env_id": env_p.id, "variant": meta.get("variant"), "seed": seed, "episodes": cfg.episodes,
        "population": len(members), "children": sum(m.origin == "child" for m in members),
        "iterations": max(m.iteration for m in members),
        "env_samples_extraction": max(m.env_samples for m in members),
        "env_samples_evaluation": sum(r.env_samples for r in results),
        **summary,
        "extraction_hypervolume": hypervolume(non_dominated(extract_returns), ref),
        "reference_point": ref.tolist(),
    }
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "evaluated.csv", evaluated_csv(members, results, on_front))
    write_text_atomic(out / "front.csv", front_csv(members, means, on_front))
    write_text_atomic(out / "metrics.json", json.dumps(_finite(metrics), indent=2) + "\n")


def _reference_point(ref: list[float] | None, n_objectives: int, params: Path) -> np.ndarray:
    if ref is None:
        raise ParamsError(f"{params}: env.reference_point is missing; evaluate needs one value per objective "
                          f"({n_objectives}), each worse than any policy scores (see docs/reference_points.md)")
    if len(ref) != n_objectives:
        raise ParamsError(f"{params}: env.reference_point = {ref} has {len(ref)} values, the env has {n_objectives} objectives")
    return np.asarray(ref, dtype=float)


def _check_population(path: Path, members, meta: dict, env_id: str, seed: int) -> None:
    if meta.get("env_id") != env_id:
        raise ArtifactError(f"{path}: population is for env {meta.get('env_id')!r}, params env.id is {env_id!r}")
    if meta.get("seed") is not None and meta["seed"] != seed:
        raise ArtifactError(f"{path}: population was extracted with seed {meta['seed']}, --seed is {seed}")
    if not members:
        raise ArtifactError(f"{path}: population has no members")


def _finite(obj):
    """JSON-safe copy: NaN and infinities become null (json would write invalid `NaN`)."""
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_finite(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _rows_to_csv(header: list[str], rows: list[list]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    w.writerows(rows)
    return buf.getvalue()


def evaluated_csv(members, results, on_front: np.ndarray) -> str:
    """One row per member; see the module docstring for the columns. Floats at full precision."""
    n_obj = len(members[0].returns)
    header = ["id", "origin", "objective", "iteration", "parents", "env_samples"]
    header += [f"obj{m}_extract" for m in range(n_obj)] + [f"obj{m}" for m in range(n_obj)]
    header += [f"obj{m}_std" for m in range(n_obj)] + ["on_front"]
    rows = []
    for i, (mem, res, front) in enumerate(zip(members, results, on_front)):
        objective = "" if mem.objective is None else mem.objective
        rows.append([i, mem.origin, objective, mem.iteration, ";".join(map(str, mem.parents)), mem.env_samples,
                     *map(float, mem.returns), *map(float, res.mean), *map(float, res.std), int(front)])
    return _rows_to_csv(header, rows)


def front_csv(members, means: np.ndarray, on_front: np.ndarray) -> str:
    """The non-dominated members sorted by obj0: id, origin, iteration, obj<m>."""
    ids = sorted(np.flatnonzero(on_front), key=lambda i: tuple(means[i]))
    header = ["id", "origin", "iteration", *(f"obj{m}" for m in range(means.shape[1]))]
    rows = [[i, members[i].origin, members[i].iteration, *map(float, means[i])] for i in ids]
    return _rows_to_csv(header, rows)
