"""Per-env facts, read from one data file, presets/envs.yaml: hypervolume reference points,
objective names, the paper's MAPEX values per env and MOPDERL's per-env budget and episodes.

The file holds one mapping per fact (env id -> value), so a DVC stage lists only the fact it
reads as a param of that file (`presets/envs.yaml: [reference_point]`, ...): editing one env's
reference point reruns the scores and nothing that trains.

Which file: presets/envs.yaml of the working directory (a DVC stage's cwd is the repository root,
so that is the file DVC tracks); where the working directory has none (a library caller or a test
elsewhere), the one of the checkout this module is in.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from pipeline.params import ParamsError

TABLE = Path("presets/envs.yaml")  # relative to the repository root (a DVC stage's cwd)
FACTS = ("reference_point", "objective_names", "paper_extract", "mopderl")
PAPER_EXTRACT_KEYS = ("epochs", "beta", "omega_max")
MOPDERL_KEYS = ("total_frames", "eval_episodes")


def table_path() -> Path:
    """presets/envs.yaml of the working directory, else of this checkout."""
    return TABLE if TABLE.is_file() else Path(__file__).resolve().parents[2] / TABLE


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _check(table: Path, fact: str, env_id: str, value: Any) -> None:
    """One line naming the file, the key and the value where an entry is not of its fact's shape."""
    where = f"{table}: {fact}.{env_id} = {value!r}"
    if fact == "reference_point" and not (isinstance(value, list) and value and all(map(_number, value))):
        raise ParamsError(f"{where}: expected a list of numbers, one per objective")
    if fact == "objective_names" and not (isinstance(value, list) and value and all(isinstance(v, str) for v in value)):
        raise ParamsError(f"{where}: expected a list of names, one per objective")
    keys = {"paper_extract": PAPER_EXTRACT_KEYS, "mopderl": MOPDERL_KEYS}.get(fact)
    if keys and not (isinstance(value, dict) and set(value) == set(keys) and all(map(_number, value.values()))):
        raise ParamsError(f"{where}: expected a mapping of {list(keys)} to numbers")


def read_facts(fact: str, table: Path | None = None) -> dict[str, Any]:
    """The mapping env id -> value of `fact` (one of FACTS) in `table` (default `table_path()`);
    ParamsError naming the file (and the key and value) if it is missing, not YAML, lacks the fact
    or holds an entry of the wrong shape."""
    if fact not in FACTS:
        raise ValueError(f"unknown per-env fact {fact!r}: expected one of {list(FACTS)}")
    table = table_path() if table is None else table
    if not table.is_file():
        raise ParamsError(f"{table}: file not found (the per-env facts: reference points, objective names, ...)")
    try:
        raw = yaml.safe_load(table.read_text())
    except yaml.YAMLError as exc:
        raise ParamsError(f"{table}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(raw, dict) or not isinstance(raw.get(fact), dict):
        raise ParamsError(f"{table}: expected a mapping `{fact}` of env ids to values (and {list(FACTS)})")
    for env_id, value in raw[fact].items():
        _check(table, fact, str(env_id), value)
    return {str(k): v for k, v in raw[fact].items()}


def reference_points(table: Path | None = None) -> dict[str, list[float]]:
    """env id -> its hypervolume reference point."""
    return {k: [float(v) for v in p] for k, p in read_facts("reference_point", table).items()}


def objective_names_of(env_id: str, table: Path | None = None) -> list[str] | None:
    """The env's objective names, None where the file has none."""
    names = read_facts("objective_names", table).get(env_id)
    return None if names is None else list(names)


def paper_extract(env_id: str, table: Path | None = None) -> tuple[int, float, float] | None:
    """(epochs, beta, omega_max) of the paper's table for the env, None where it has none."""
    entry = read_facts("paper_extract", table).get(env_id)
    if entry is None:
        return None
    return int(entry["epochs"]), float(entry["beta"]), float(entry["omega_max"])


def paper_extract_envs(table: Path | None = None) -> list[str]:
    """The envs the paper gives MAPEX values for."""
    return sorted(read_facts("paper_extract", table))


def mopderl_values(env_id: str, table: Path | None = None) -> dict[str, int] | None:
    """{total_frames, eval_episodes} of MOPDERL for the env, None where the file has none."""
    entry = read_facts("mopderl", table).get(env_id)
    return None if entry is None else {k: int(entry[k]) for k in MOPDERL_KEYS}
