"""Evaluated runs, the report's input: `Run`, one (method, seed) with the evaluate stage's
re-evaluated returns, the score stage's metrics, front and hypervolume history, and the
provenance records of the stages that made it; the methods' names and their usual order; and
the loaders that read every run from the score and evaluate outputs and the provenance records
(`load_runs`, `load_run`, `read_provenance`, `check_comparable`), raising ArtifactError that
names the file on a bad input."""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core.artifacts import ArtifactError, read_json
from pipeline.reporting.presentation import METHOD_ORDER, VARIANT_METHODS

RUN_DIR = re.compile(r"^seed(\d+)$")
METRICS_KEYS = (
    "env_id",
    "method",
    "seed",
    "episodes",
    "front",
    "specialists",
    "hv_ratio_vs_specialists",
    "extraction_hypervolume",
    "iterations",
    "env_samples_extraction",
    "reference_point",
)
FRONT_KEYS = (
    "hypervolume",
    "hv_fraction",
    "sparsity",
    "sparsity_pgmorl",
    "expected_utility",
    "cardinality",
    "distinct_count",
)
HISTORY_COLUMNS = ("iteration", "env_samples", "hypervolume_extract", "hypervolume")
# Where each stage of a run (METHOD, seed S) records what produced it, below the provenance root
# (dvc.yaml: data/provenance): ROOT/<folder>/METHOD/seedS.json, the folder being that of the
# stage's outputs below data/. "extract" is the stage that made the population: extract, or the
# baselines' mopderl and morld, all of which write data/fronts/METHOD/seedS.
PROVENANCE_FOLDERS = {"extract": "fronts", "evaluate": "evaluate", "score": "score"}


@dataclass
class Run:
    """One evaluated extraction run."""

    method: str  # pipeline/params/methods.py
    seed: int
    metrics: dict  # the score stage's metrics.json
    returns: np.ndarray  # (n, m) re-evaluated mean return of each member
    origin: (
        np.ndarray
    )  # (n,) "specialist" (a starting policy, from a specialist's policy set) or what made it ("child", ...)
    iteration: np.ndarray  # (n,) iteration that made the member (0 for starting policies)
    on_front: np.ndarray  # (n,) bool, non-dominated among `returns`
    # the score stage's hypervolume.csv: iteration, env_samples, hypervolume_extract, hypervolume (each (T,))
    history: dict[str, np.ndarray]
    provenance: dict | None = None  # PROVENANCE_FOLDERS' stage -> its pipeline.core.provenance record or None
    objective: np.ndarray | None = None  # (n,) the specialist a starting policy came from, -1 for a child

    def starting_counts(self) -> dict[int, int]:
        """Number of starting policies per specialist objective (1 each for TD3 specialists)."""
        spec = self.origin == "specialist"
        objectives = self.objective[spec] if self.objective is not None else np.full(int(spec.sum()), -1)
        keys, counts = np.unique(objectives, return_counts=True)
        return {int(k): int(c) for k, c in zip(keys, counts)}


def methods_in(runs: list[Run]) -> list[str]:
    """Variants present, the known ones first in their usual order."""
    present = {r.method for r in runs}
    # the variants of the params file after the built-in methods (a built-in variant is both: once)
    order = tuple(dict.fromkeys((*METHOD_ORDER, *VARIANT_METHODS)))
    return [v for v in order if v in present] + sorted(present - set(order))


def load_runs(scored: Path, evaluated: Path, provenance: Path | None = None) -> list[Run]:
    """Every SCORED/VARIANT/seedS with a metrics.json, with its score outputs, evaluated.csv and
    the provenance records under PROVENANCE (none: every record 'not recorded')."""
    if not scored.is_dir():
        raise ArtifactError(f"{scored}: not a directory of score outputs")
    runs = []
    for metrics_path in sorted(scored.glob("*/seed*/metrics.json")):
        run_dir = metrics_path.parent
        match = RUN_DIR.match(run_dir.name)
        if match is None:
            continue
        runs.append(
            load_run(
                run_dir,
                evaluated / run_dir.parent.name / run_dir.name,
                run_dir.parent.name,
                int(match.group(1)),
                provenance,
            )
        )
    if not runs:
        raise ArtifactError(f"{scored}: no VARIANT/seedS/metrics.json found (run the score stage first)")
    return runs


def load_run(score_dir: Path, eval_dir: Path, method: str, seed: int, provenance: Path | None = None) -> Run:
    """One run from its score folder, evaluate folder and provenance root (read_provenance);
    ArtifactError naming the file on a bad input."""
    metrics = read_json(score_dir / "metrics.json", METRICS_KEYS)
    for group in ("front", "specialists"):
        missing = [k for k in FRONT_KEYS if k not in (metrics[group] if isinstance(metrics[group], dict) else {})]
        if missing:
            raise ArtifactError(f"{score_dir / 'metrics.json'}: no {', '.join(f'{group}.{k}' for k in missing)} key")
    if (metrics["method"], metrics["seed"]) != (method, seed):
        raise ArtifactError(
            f"{score_dir / 'metrics.json'}: is for method {metrics['method']!r} seed {metrics['seed']!r}, "
            f"but sits in {method}/seed{seed}"
        )
    members = _read_csv(eval_dir / "evaluated.csv", ["origin", "iteration", "obj0", "obj1"])
    n_obj = sum(1 for k in members if re.fullmatch(r"obj\d+", k))
    front = _read_csv(score_dir / "front.csv", ["id"], allow_empty=True)
    hist = _read_csv(score_dir / "hypervolume.csv", list(HISTORY_COLUMNS))
    try:
        ids = np.asarray(front.get("id", []), int)
        on_front = np.zeros(len(members["origin"]), bool)
        on_front[ids] = True
        return Run(
            method=method,
            seed=seed,
            metrics=metrics,
            returns=np.stack([np.asarray(members[f"obj{m}"], float) for m in range(n_obj)], axis=1),
            origin=np.asarray(members["origin"]),
            iteration=np.asarray(members["iteration"], int),
            on_front=on_front,
            history={k: np.asarray(hist[k], float) for k in HISTORY_COLUMNS},
            provenance=read_provenance(provenance, method, seed),
            objective=np.array(
                [int(x) if x != "" else -1 for x in members.get("objective", [""] * len(members["origin"]))]
            ),
        )
    except (ValueError, IndexError) as exc:
        raise ArtifactError(
            f"{score_dir}: front.csv, hypervolume.csv or {eval_dir / 'evaluated.csv'} "
            f"do not fit together or hold unreadable numbers ({exc})"
        ) from None


def read_provenance(root: Path | None, method: str, seed: int) -> dict[str, dict | None]:
    """Per stage of PROVENANCE_FOLDERS, the record ROOT/<folder>/METHOD/seedS.json that stage
    wrote (pipeline.core.provenance), or None where there is none: no ROOT given, or the stage
    was run without --provenance (by hand, outside DVC). A record that exists but cannot be
    read is an ArtifactError naming the file."""
    records: dict[str, dict | None] = {}
    for stage, folder in PROVENANCE_FOLDERS.items():
        path = None if root is None else root / folder / method / f"seed{seed}.json"
        records[stage] = read_json(path) if path is not None and path.exists() else None
    return records


def check_comparable(scored: Path, runs: list[Run], env_id: str) -> None:
    """Every run is for params env.id and was scored against one reference point."""
    envs = sorted({str(r.metrics["env_id"]) for r in runs})
    if envs != [env_id]:
        raise ArtifactError(f"{scored}: runs are for env(s) {envs}, params env.id is {env_id!r}")
    refs = {tuple(r.metrics["reference_point"]) for r in runs}
    derived = all(str(r.metrics.get("reference_point_source", "")).startswith("auto") for r in runs)
    if len(refs) > 1 and not derived:  # points derived per run (auto) differ by design: the report warns
        raise ArtifactError(
            f"{scored}: runs were scored against different reference points {sorted(refs)}; rerun score"
        )


def _read_csv(path: Path, required: list[str], allow_empty: bool = False) -> dict[str, list[str]]:
    """Columns of a CSV file by name; ArtifactError naming the file if it is missing, empty or lacks a column."""
    if not path.is_file():
        raise ArtifactError(f"{path}: file not found")
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        rows = list(reader)
        header = reader.fieldnames or []
    if not rows and not allow_empty:
        raise ArtifactError(f"{path}: no rows")
    missing = [c for c in required if c not in header]
    if missing:
        raise ArtifactError(f"{path}: missing column(s) {missing}")
    return {k: [r[k] for r in rows] for k in header}
