"""Which hypervolume reference point a run is scored against, and where it came from.

`env.reference_point` in params wins where it is set. Where it is null (the default), the env's
entry in the table presets/reference_points.yaml is used (one point per env, derived in
docs/reference_points.md), so `dvc exp run -S env.id=...` scores against that env's point
rather than the last one written into params.yaml. An env without an entry stops scoring with
one line that says what to set.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from pipeline.params import ParamsError

TABLE = Path("presets/reference_points.yaml")  # relative to the repository root (a DVC stage's cwd)


@dataclass(frozen=True)
class ReferencePoint:
    point: np.ndarray  # (n_objectives,)
    source: str  # where it came from, in words (the report prints it)


def read_table(table: Path) -> dict[str, list[float]]:
    """The table env id -> reference point; ParamsError naming the file if it is missing or
    is not a mapping of env ids to lists of numbers."""
    if not table.is_file():
        raise ParamsError(f"{table}: file not found (the table of reference points per env)")
    try:
        raw = yaml.safe_load(table.read_text())
    except yaml.YAMLError as exc:
        raise ParamsError(f"{table}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(raw, dict):
        raise ParamsError(f"{table}: expected a mapping of env ids to reference points")
    for env_id, point in raw.items():
        if not isinstance(point, list) or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in point
        ):
            raise ParamsError(f"{table}: {env_id} = {point!r} is not a list of numbers")
    return {str(k): [float(v) for v in p] for k, p in raw.items()}


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
        entries = read_table(table)
        if env_id not in entries:
            raise ParamsError(
                f"{params}: env.reference_point is null and {table} has no entry for {env_id!r}: set "
                f"env.reference_point to {n_objectives} values, each worse than any policy scores "
                "(docs/reference_points.md)"
            )
        point = entries[env_id]
        source = f"{table.as_posix()}, entry {env_id} (env.reference_point is null)"
        where = f"{table}: {env_id} = {point} (env.reference_point is null in {params})"
    if len(point) != n_objectives:
        raise ParamsError(f"{where} has {len(point)} values, the env has {n_objectives} objectives")
    return ReferencePoint(np.asarray(point, dtype=float), source)
