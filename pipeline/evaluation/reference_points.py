"""Which hypervolume reference point a run is scored against, and where it came from.

`env.reference_point` in params wins where it is set. Where it is null (the default), the env's
entry in presets/envs.yaml (`reference_point`, pipeline/params/env_facts.py; one point per env,
derived in docs/reference_points.md) is used, so `dvc exp run -S env.id=...` scores against that env's point
rather than the last one written into params.yaml. An env without an entry stops scoring with
one line that says what to set.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.params import ParamsError
from pipeline.params.env_facts import TABLE, reference_points


@dataclass(frozen=True)
class ReferencePoint:
    point: np.ndarray  # (n_objectives,)
    source: str  # where it came from, in words (the report prints it)


def resolve_reference_point(
    given: list[float] | None, env_id: str, n_objectives: int, params: Path, table: Path = TABLE
) -> ReferencePoint:
    """The point `given` (params env.reference_point) if set, else ENV_ID's entry in `table`,
    with one value per objective. ParamsError naming the file and key otherwise: a wrong length,
    or null with no entry for the env (one line saying what to set)."""
    if given is not None:
        point, source = given, "env.reference_point in params"
        where = f"{params}: env.reference_point = {given}"
    else:
        entries = reference_points(table)
        if env_id not in entries:
            raise ParamsError(
                f"{params}: env.reference_point is null and {table} has no reference_point for {env_id!r}: set "
                f"env.reference_point to {n_objectives} values, each worse than any policy scores "
                "(docs/reference_points.md)"
            )
        point = entries[env_id]
        source = f"{table.as_posix()}, entry {env_id} (env.reference_point is null)"
        where = f"{table}: reference_point.{env_id} = {point} (env.reference_point is null in {params})"
    if len(point) != n_objectives:
        raise ParamsError(f"{where} has {len(point)} values, the env has {n_objectives} objectives")
    return ReferencePoint(np.asarray(point, dtype=float), source)
