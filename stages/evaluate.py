"""Stage evaluate: re-evaluate every member of a final population on fresh episodes.

Only the episodes run here; the `score` stage turns their returns into a front and metrics,
so a change to a metric's setting or to env.reference_point reruns no episode.

Outputs (in OUT):
  evaluated.csv    one row per member (every starting policy and every child): id, origin,
                   objective and policy_name (a starting policy's specialist and its name in that
                   specialist's policy set; empty for a child), iteration, parents (';'-joined),
                   env_samples, obj<m>_extract (extraction-time mean return), obj<m> and obj<m>_std
                   (re-evaluated mean and std over `evaluate.episodes` episodes). Columns are named
                   obj0, obj1, ... rather than after the objectives so dvc.yaml's plot axes fit every env.
  evaluation.json  what was run: env_id, method, seed, episodes, seed_stream, max_episode_steps,
                   population, env_samples_evaluation.
What produced the run (pipeline.core.provenance) goes to the --provenance file, outside OUT.
"""

from __future__ import annotations

import json
import multiprocessing as mp
from pathlib import Path
from typing import Optional

import numpy as np
import torch
import typer

from pipeline.core.artifacts import ArtifactError, csv_text, write_text_atomic
from pipeline.core.envs import env_spec, make_env
from pipeline.core.population import Member, load_population, member_actor
from pipeline.core.precision import resolve
from pipeline.core.provenance import write_provenance
from pipeline.core.seeding import select_device
from pipeline.evaluation.episodes import EvalResult, eval_seeds, evaluate_policy
from pipeline.params import ParamsError
from pipeline.params.evaluate import EvaluateParams
from stages.common import (
    PARAMS_OPTION,
    PROVENANCE_OPTION,
    fmt_vec,
    progress,
    read_params,
    reports_errors,
    run_parts,
)

META_KEYS = ("env_id", "obs_dim", "act_dim", "n_objectives", "action_low", "action_high", "seed", "method")


@reports_errors
def evaluate(
    population: Path = typer.Option(..., help="population.pt written by the extract stage"),
    out: Path = typer.Option(..., help="output directory (evaluated.csv, evaluation.json)"),
    seed: int = typer.Option(0, help="run seed of the population (must match its metadata)"),
    params: Path = PARAMS_OPTION,
    provenance: Optional[Path] = PROVENANCE_OPTION,
) -> None:
    """Re-evaluate every member of an extracted population on fresh episode seeds.

    Every member: each starting policy (all of every specialist's policy set) and each child.
    Params: sections `env` (id, max_episode_steps) and `evaluate`. Each member runs
    `evaluate.episodes` deterministic episodes whose seeds differ from extraction's
    (`evaluate.seed_stream`). `evaluate.processes` > 1 deals the members to that many worker
    processes side by side (the same results). Nothing is scored here: run `mapex score` on the outputs.

    Writes to OUT: evaluated.csv (one row per member: extraction-time and re-evaluated returns;
    a `dvc plots` scatter of obj0 vs obj1) and evaluation.json (what was run); with --provenance,
    what produced the run (pipeline.core.provenance) to that file, outside OUT.
    """
    _, env_p, cfg, _ = read_params(params, "evaluate", EvaluateParams)
    members, meta = load_population(population, META_KEYS)
    _check_population(population, members, meta, env_p.id, seed)
    try:
        device = select_device(cfg.device)
    except ValueError as exc:
        raise ParamsError(f"{params}: evaluate.device: {exc}") from None
    precision = resolve(cfg.precision, device, 0, workload="act")
    envs = [make_env(env_p.id, env_p.max_episode_steps, env_p.reward_terms) for _ in range(cfg.episodes)]
    spec = env_spec(envs[0], env_p.id, env_p.max_episode_steps)
    dims = (meta["obs_dim"], meta["act_dim"], meta["n_objectives"])
    if (spec.obs_dim, spec.act_dim, spec.n_objectives) != dims:
        raise ArtifactError(
            f"{population}: dims (obs, act, objectives) {dims} "
            f"do not match env {env_p.id} {(spec.obs_dim, spec.act_dim, spec.n_objectives)}"
        )

    processes = min(cfg.processes, len(members)) if device.type == "cpu" else 1
    results: list[EvalResult | None] = [None] * len(members)
    with progress(len(members), f"evaluate {meta['method']} seed {seed}", unit="policy") as bar:

        def done(part: int, result: tuple[int, EvalResult]) -> None:
            i, res = result
            results[i] = res
            bar.set_postfix_str(f"{members[i].origin} {i} return {fmt_vec(res.mean)}", refresh=False)
            bar.update(1)

        if processes == 1:
            for i, member in enumerate(members):
                res = evaluate_policy(
                    member_actor(member, meta).to(device),
                    envs,
                    eval_seeds(seed, cfg.seed_stream, i, cfg.episodes),
                    precision,
                )
                done(0, (i, res))
        else:
            for env in envs:  # each worker makes its own
                env.close()
            envs = []
            # Members dealt round robin, so a part of long and short episodes (a hopper that falls)
            # is as likely as the other. Forked on a CPU with one torch thread: the workers start
            # with this process's imports (pipeline.core.workers says when a fork is safe).
            start = "fork" if torch.get_num_threads() == 1 and "fork" in mp.get_all_start_methods() else "spawn"
            parts = [
                ([(i, members[i]) for i in range(p, len(members), processes)], meta, env_p.id, env_p.max_episode_steps,
                 env_p.reward_terms, seed, cfg.seed_stream, cfg.episodes, precision)
                for p in range(processes)
            ]  # fmt: skip
            run_parts(_evaluate_part, parts, bar, lambda p: f"evaluate part {p}", on_result=done, start=start)
    for env in envs:
        env.close()

    record = {
        "env_id": env_p.id,
        "method": meta["method"],
        "seed": seed,
        "episodes": cfg.episodes,
        "seed_stream": cfg.seed_stream,
        "max_episode_steps": env_p.max_episode_steps,
        "population": len(members),
        "env_samples_evaluation": sum(r.env_samples for r in results),
    }
    if precision != "fp32":  # an fp32 record stays as it was before the key existed
        record["precision"] = precision
    out.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out / "evaluated.csv", evaluated_csv(members, results))
    write_text_atomic(out / "evaluation.json", json.dumps(record, indent=2) + "\n")
    write_provenance(provenance, "evaluate", device, precision)


def _evaluate_part(
    members: list[tuple[int, Member]],
    meta: dict,
    env_id: str,
    max_episode_steps: int,
    reward_terms: list | None,
    seed: int,
    seed_stream: int,
    episodes: int,
    precision: str,
    threads: int,
    send,
) -> None:
    """A worker's share of the members (index, member): each evaluated exactly as the stage's own
    loop does (the same envs' make, the same seeds, on the CPU), sent back as ("result", (index,
    EvalResult))."""
    torch.set_num_threads(threads)
    envs = [make_env(env_id, max_episode_steps, reward_terms) for _ in range(episodes)]
    try:
        for i, member in members:
            res = evaluate_policy(
                member_actor(member, meta), envs, eval_seeds(seed, seed_stream, i, episodes), precision
            )
            send("result", (i, res))
    finally:
        for env in envs:
            env.close()


def _check_population(path: Path, members: list[Member], meta: dict, env_id: str, seed: int) -> None:
    if meta["env_id"] != env_id:
        raise ArtifactError(f"{path}: population is for env {meta['env_id']!r}, params env.id is {env_id!r}")
    if meta["seed"] != seed:
        raise ArtifactError(f"{path}: population was extracted with seed {meta['seed']}, --seed is {seed}")
    if not members:
        raise ArtifactError(f"{path}: population has no members")


def evaluated_csv(members: list[Member], results: list[EvalResult]) -> str:
    """One row per member; see the module docstring for the columns. Floats at full precision
    (Python's repr, so they read back bit for bit)."""
    n_obj = len(members[0].returns)
    header = ["id", "origin", "objective", "policy_name", "iteration", "parents", "env_samples"]
    header += [f"obj{m}_extract" for m in range(n_obj)] + [f"obj{m}" for m in range(n_obj)]
    header += [f"obj{m}_std" for m in range(n_obj)]
    rows = []
    for i, (mem, res) in enumerate(zip(members, results)):
        objective = "" if mem.objective is None else mem.objective
        rows.append(
            [
                i,
                mem.origin,
                objective,
                mem.policy_name or "",
                mem.iteration,
                ";".join(map(str, mem.parents)),
                mem.env_samples,
                *map(float, mem.returns),
                *map(float, np.asarray(res.mean)),
                *map(float, np.asarray(res.std)),
            ]
        )
    return csv_text(header, rows)
