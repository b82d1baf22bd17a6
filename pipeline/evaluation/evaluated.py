"""Reading the evaluate stage's outputs back (evaluated.csv, evaluation.json) for a population:
the re-evaluated returns, checked to describe that population member by member (stages score
and export)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from pipeline.core.artifacts import ArtifactError
from pipeline.core.population import Member

META_KEYS = ("env_id", "n_objectives", "seed", "method")
EVALUATION_KEYS = ("env_id", "method", "seed", "episodes", "population", "env_samples_evaluation")


def read_evaluated(path: Path, members: list[Member], n_obj: int) -> np.ndarray:
    """Re-evaluated mean returns (n, m) from evaluated.csv, after checking that its rows are
    `members` in order (same origin, iteration and, bit for bit, extraction-time returns)."""
    if not path.is_file():
        raise ArtifactError(f"{path}: file not found")
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    objs = [f"obj{m}" for m in range(n_obj)]
    needed = ["id", "origin", "iteration", *objs, *(f"{c}_extract" for c in objs)]
    missing = [c for c in needed if rows and c not in rows[0]]
    if missing:
        raise ArtifactError(f"{path}: missing column(s) {missing}")
    if len(rows) != len(members):
        raise ArtifactError(f"{path}: {len(rows)} rows, but the population has {len(members)} members")
    try:
        for i, (row, mem) in enumerate(zip(rows, members)):
            mine = (int(row["id"]), row["origin"], int(row["iteration"]), [float(row[f"{c}_extract"]) for c in objs])
            if mine != (i, mem.origin, mem.iteration, [float(x) for x in mem.returns]):
                raise ArtifactError(
                    f"{path}: row {i} does not describe member {i} of the population "
                    f"(id, origin, iteration, extraction-time returns differ); rerun evaluate"
                )
        return np.array([[float(row[c]) for c in objs] for row in rows])
    except ValueError as exc:
        raise ArtifactError(f"{path}: unreadable number ({exc})") from None


def check_same_run(path: Path, record: dict, population: Path, meta: dict, n_members: int) -> None:
    """evaluation.json must describe this population: same env, method, seed and size."""
    theirs = {k: record[k] for k in ("env_id", "method", "seed", "population")}
    ours = {"env_id": meta["env_id"], "method": meta["method"], "seed": meta["seed"], "population": n_members}
    if theirs != ours:
        differ = [k for k in ours if theirs[k] != ours[k]]
        raise ArtifactError(
            f"{path} ({', '.join(f'{k} = {theirs[k]!r}' for k in differ)}) does not describe "
            f"{population} ({', '.join(f'{k} = {ours[k]!r}' for k in differ)})"
        )


def read_std(path: Path, n_obj: int) -> np.ndarray:
    """The per-objective spread (std over the evaluation episodes) of each member, (n, m)."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    cols = [f"obj{m}_std" for m in range(n_obj)]
    if rows and any(c not in rows[0] for c in cols):
        raise ArtifactError(f"{path}: missing column(s) {[c for c in cols if c not in rows[0]]}")
    return np.array([[float(r[c]) for c in cols] for r in rows]).reshape(len(rows), n_obj)
