"""What each front cost, from the provenance records the stages wrote (pipeline.core.cost): the
core-seconds of the stage that made a method's population, of its re-evaluation, and of the
specialists it started from; the report's cost table, the cost column beside the verdicts and
the figure of re-evaluated hypervolume against cumulative core-seconds.

A method's core-seconds are its producing stage's (extract, interpolate, mopderl, morld):
- where the record has per-iteration rows (extraction and interpolation: "cost" ->
  "iterations"), their sum: training and evaluating every member, the starting policies'
  evaluation and the hybrid extraction's interpolated seeds included (their own row, phase
  "seeds"); the rows survive a resume, so a resumed run counts every iteration once;
- otherwise the stage process's CPU seconds ("cost" -> "cpu_seconds"; a resumed run: its last
  process only).
Loading the inputs (buffers, critics) is in the process's seconds but in no row. Core-seconds
are CPU seconds: a GPU's own time is not in them (the provenance table names the device).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from pipeline.core.artifacts import ArtifactError
from pipeline.evaluation.metrics import mean_sem
from pipeline.reporting.presentation import label, specialist_kind
from pipeline.reporting.runs import Run, methods_in
from pipeline.reporting.tables import _md_table

CPU_KEYS = ("train_cpu_s", "eval_cpu_s")


def _cost(record: dict | None) -> dict | None:
    cost = (record or {}).get("cost")
    return cost if isinstance(cost, dict) else None


def iteration_rows(run: Run) -> list[dict]:
    """The per-iteration cost rows of the run's producing stage ([] where it recorded none)."""
    rows = (_cost((run.provenance or {}).get("extract")) or {}).get("iterations")
    return rows if isinstance(rows, list) else []


def method_core_seconds(run: Run) -> float | None:
    """The run's method's core-seconds (the module docstring says which); None if unrecorded."""
    rows = iteration_rows(run)
    if rows:
        return float(sum(r[k] for r in rows for k in CPU_KEYS))
    cost = _cost((run.provenance or {}).get("extract"))
    return float(cost["cpu_seconds"]) if cost and "cpu_seconds" in cost else None


def part_core_seconds(
    run: Run, phases: tuple[str, ...] | None = None, keys: tuple[str, ...] = CPU_KEYS
) -> float | None:
    """The core-seconds of the rows of `phases` (None: every phase) and columns `keys`; None
    without rows."""
    rows = iteration_rows(run)
    if not rows:
        return None
    return float(sum(r[k] for r in rows if phases is None or r["phase"] in phases for k in keys))


def stage_seconds(run: Run, stage: str, key: str = "cpu_seconds") -> float | None:
    """A stage's process seconds (`key`: cpu_seconds or wall_seconds) from its record; None if unrecorded."""
    cost = _cost((run.provenance or {}).get(stage))
    return float(cost[key]) if cost and key in cost else None


def cost_curve(run: Run) -> tuple[np.ndarray, np.ndarray] | None:
    """(cumulative core-seconds, re-evaluated hypervolume) after each iteration of the run's
    hypervolume history, from its per-iteration cost rows; None without rows."""
    rows = iteration_rows(run)
    if not rows:
        return None
    spent: dict[int, float] = {}
    for r in rows:
        spent[int(r["iteration"])] = spent.get(int(r["iteration"]), 0.0) + sum(r[k] for k in CPU_KEYS)
    its = run.history["iteration"].astype(int)
    cumulative = np.cumsum([spent.get(int(i), 0.0) for i in range(int(its.max()) + 1)])
    return cumulative[its], run.history["hypervolume"]


def read_specialist_costs(root: Path | None, runs: list[Run]) -> dict[tuple[str, int], float]:
    """(kind, seed) -> the core-seconds of that seed's specialists of that kind, summed over
    their records under ROOT/specialists (td3 and pderl: <kind>/seedS.json; imported, one per
    objective: imported/seedS/*.json, collection and training of the objectives an import left
    out); a (kind, seed) without a record is left out. An unreadable record: ArtifactError."""
    out: dict[tuple[str, int], float] = {}
    if root is None:
        return out
    for kind, seed in {(specialist_kind(r.method), r.seed) for r in runs} - {(None, r.seed) for r in runs}:
        base = root / "specialists" / kind
        files = [base / f"seed{seed}.json"] if kind != "imported" else sorted((base / f"seed{seed}").glob("*.json"))
        total, found = 0.0, False
        for f in files:
            if not f.is_file():
                continue
            try:
                cost = _cost(json.loads(f.read_text()))
            except (OSError, json.JSONDecodeError) as exc:
                raise ArtifactError(f"{f}: cannot be read as JSON ({exc})") from None
            if cost and "cpu_seconds" in cost:
                total, found = total + float(cost["cpu_seconds"]), True
        if found:
            out[(kind, seed)] = total
    return out


def seconds(x: float, like: float | None = None) -> str:
    """Seconds to about three figures: '1,234', '56.7', '0.12' (decimals as for `like`, default x)."""
    size = abs(x if like is None else like)
    return f"{x:,.0f}" if size >= 100 else f"{x:.1f}" if size >= 10 else f"{x:.2f}"


def fmt_seconds(values: list[float | None]) -> str:
    """'1,234 ± 56' seconds over seeds (`seconds`; 'n/a' where none recorded; '(k of n seeds)' where some)."""
    v = [x for x in values if x is not None]
    if not v:
        return "n/a"
    mean, sem = mean_sem(v)
    text = seconds(mean) if len(v) < 2 else f"{seconds(mean)} ± {seconds(sem, mean)}"
    return text if len(v) == len(values) else f"{text} ({len(v)} of {len(values)} seeds)"


def mean_cost(runs: list[Run], method: str) -> float | None:
    """The mean over seeds of a method's core-seconds (None if no seed recorded it)."""
    v = [c for r in runs if r.method == method if (c := method_core_seconds(r)) is not None]
    return float(np.mean(v)) if v else None


def cost_table(runs: list[Run], specialists: dict[tuple[str, int], float]) -> str:
    """Per method: core-seconds making the front (of which training, evaluating, and the hybrid
    extraction's interpolated seeds), its wall seconds, the re-evaluation's core-seconds, and
    the extensions' record (early stop, fallbacks; those three columns only where a run has
    them); then per kind of specialists their core-seconds per seed. '' when no run recorded a
    cost, an early stop or fallbacks."""
    extensions = any("stopped_at" in r.metrics or "init_fallbacks" in r.metrics for r in runs)
    if not any(method_core_seconds(r) is not None for r in runs) and not specialists and not extensions:
        return ""
    header = [
        "Method",
        "seeds",
        "core-s making the front",
        "of which training",
        "of which evaluating",
        "of which interpolated seeds",
        "wall s",
        "core-s re-evaluating",
        "stopped early after iteration",
        "children that fell back to warm-up",
    ]
    rows = []
    for v in methods_in(runs):
        rs = [r for r in runs if r.method == v]
        stops = [r.metrics.get("stopped_at") for r in rs if "stopped_at" in r.metrics]
        falls = [sum((r.metrics.get("init_fallbacks") or {}).values()) for r in rs if "init_fallbacks" in r.metrics]
        seeds = [part_core_seconds(r, ("seeds",)) for r in rs]
        rows.append(
            [
                label(v),
                str(len(rs)),
                fmt_seconds([method_core_seconds(r) for r in rs]),
                fmt_seconds([part_core_seconds(r, None, ("train_cpu_s",)) for r in rs]),
                fmt_seconds([part_core_seconds(r, None, ("eval_cpu_s",)) for r in rs]),
                fmt_seconds(seeds) if any(s for s in seeds) else "",
                fmt_seconds([stage_seconds(r, "extract", "wall_seconds") for r in rs]),
                fmt_seconds([stage_seconds(r, "evaluate") for r in rs]),
                ", ".join("not stopped" if s is None else str(s) for s in stops) if stops else "",
                f"{sum(falls)} of {sum(int((r.origin == 'child').sum()) for r in rs if 'init_fallbacks' in r.metrics)}"
                if falls
                else "",
            ]
        )
    for kind in sorted({k for k, _ in specialists}):
        per_seed = [specialists[(k, s)] for k, s in sorted(specialists) if k == kind]
        rows.append(
            [
                f"{kind.upper() if kind != 'imported' else 'imported'} specialists (per seed, shared by the methods of that kind)",
                str(len(per_seed)),
                fmt_seconds(per_seed),
                "",
                "",
                "",
                "",
                "",
                "",
                "",
            ]
        )
    optional = {"of which interpolated seeds", "stopped early after iteration", "children that fell back to warm-up"}
    keep = [j for j, h in enumerate(header) if h not in optional or any(r[j] for r in rows)]
    return _md_table([header[j] for j in keep], [[r[j] for j in keep] for r in rows])


def verdict_cost_table(said: list, runs: list[Run]) -> str:
    """Each verdict beside what each side cost: comparison, outcome, core-seconds of each method
    (mean over the paired seeds' runs), their ratio. '' without verdicts."""
    if not said:
        return ""
    rows = []
    for v in said:
        if v.a is None:
            continue
        ca, cb = mean_cost(runs, v.a), mean_cost(runs, v.b)
        ratio = f"{ca / cb:,.1f}x" if ca is not None and cb else "n/a"
        rows.append(
            [
                f"{label(v.a)} vs {label(v.b)}",
                {"beat": "beat", "lost": "lost to", "tied": "tied with"}.get(v.outcome, v.outcome),
                v.difference,
                fmt_seconds([ca]),
                fmt_seconds([cb]),
                ratio,
            ]
        )
    if not rows:
        return ""
    return _md_table(
        ["verdict", "outcome", "hypervolume, paired", "core-s (first)", "core-s (second)", "cost ratio"], rows
    )
