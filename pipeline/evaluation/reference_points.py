"""Which hypervolume reference point a run is scored against, and where it came from.

`env.reference_point` in params wins where it is a list. Where it is null (the default), the
env's entry in presets/envs.yaml (`reference_point`, pipeline/params/env_facts.py; one point per
env, derived in docs/reference_points.md) is used, so `dvc exp run -S env.id=...` scores against
that env's point rather than the last one written into params.yaml. An env without an entry, or
`env.reference_point: auto`, gets a point derived from the run's own starting policies
(`auto_reference_point`, the rule stated there and in docs/reference_points.md); such a point
differs from run to run, and the report says that their hypervolumes compare only within runs
that share it.
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


AUTO_SOURCE = "auto"  # how a derived point's source starts (the report tells such runs apart by it)
AUTO_MARGIN = 0.1  # of the starting policies' spread on the objective
AUTO_FLOOR = 0.01  # of the worst value's magnitude, and at least AUTO_MIN, where the spread is ~0
AUTO_MIN = 1.0


def auto_reference_point(returns: np.ndarray) -> np.ndarray:
    """The rule of `env.reference_point: auto`: per objective, the worst of `returns` (the run's
    starting policies' re-evaluated mean returns, one row each; a run with none, MORL/D, gives
    its whole population's) less a margin of 10% of their spread on that objective, and at least
    1% of the worst value's magnitude, and at least 1: every starting policy then adds volume, and
    a policy worse than all of them on an objective adds none."""
    returns = np.asarray(returns, dtype=float)
    worst, best = returns.min(axis=0), returns.max(axis=0)
    margin = np.maximum(AUTO_MARGIN * (best - worst), np.maximum(AUTO_FLOOR * np.abs(worst), AUTO_MIN))
    return worst - margin


def resolve_reference_point(
    given: list[float] | str | None,
    env_id: str,
    n_objectives: int,
    params: Path,
    table: Path = TABLE,
    starting: np.ndarray | None = None,
) -> ReferencePoint:
    """The point `given` (params env.reference_point) if a list, else ENV_ID's entry in `table`
    where `given` is null and the table lists the env, else the `auto_reference_point` of
    `starting` (the run's starting policies' returns; None at planning, which only checks). One
    value per objective: ParamsError naming the file and key otherwise."""
    entries = reference_points(table) if given is None else {}
    if given == "auto" or (given is None and env_id not in entries):
        why = "env.reference_point is auto" if given == "auto" else f"{table} has no reference_point for {env_id!r}"
        if starting is None:  # planning: the rule will apply
            return ReferencePoint(np.full(n_objectives, np.nan), f"{AUTO_SOURCE}: {why}")
        point = auto_reference_point(starting)
        return ReferencePoint(
            point,
            f"{AUTO_SOURCE}: derived from this run's {len(starting)} starting policies ({why}): the worst return on "
            "each objective less 10% of their spread (docs/reference_points.md); compares only within runs that share it",
        )
    if given is not None:
        point, source = given, "env.reference_point in params"
        where = f"{params}: env.reference_point = {given}"
    else:
        point = entries[env_id]
        source = f"{table.as_posix()}, entry {env_id} (env.reference_point is null)"
        where = f"{table}: reference_point.{env_id} = {point} (env.reference_point is null in {params})"
    if len(point) != n_objectives:
        raise ParamsError(f"{where} has {len(point)} values, the env has {n_objectives} objectives")
    return ReferencePoint(np.asarray(point, dtype=float), source)
