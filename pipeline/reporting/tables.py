"""The report's markdown tables: number formatting (mean ± SEM over seeds), the paper's Table 1
layout and the details table per method, the sample-efficiency table (env frames to reach
another method's hypervolume) and the provenance table; `_md_table` renders them all."""

from __future__ import annotations

import math

import numpy as np

from pipeline.evaluation.metrics import mean_sem
from pipeline.reporting.presentation import label, specialist_kind
from pipeline.reporting.runs import METHOD_ORDER, PROVENANCE_FOLDERS, Run, methods_in

SPECIALIST_ORDER = ("pderl", "td3", "imported")  # the report's order of the kinds of specialists


def fmt_num(x: float | None) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "n/a"
    if x != 0 and (abs(x) >= 1e4 or abs(x) < 1e-2):
        return f"{x:.2e}".replace("e+0", "e").replace("e+", "e").replace("e-0", "e-")
    return f"{x:.4g}"


def fmt_mean_sem(values: list[float | None]) -> str:
    """'mean ± SEM' over seeds; just the mean for one value; n/a when no finite value.

    A missing value (None or NaN, e.g. an undefined ratio) is left out and the cell says over
    how many of the seeds the mean is: '2.1 ± 0.3 (2 of 3 seeds)'.
    """
    v = [x for x in values if x is not None and math.isfinite(x)]
    if not v:
        return "n/a"
    mean, sem = mean_sem(v)
    text = fmt_num(mean) if len(v) < 2 else f"{fmt_num(mean)} ± {fmt_num(sem)}"
    return text if len(v) == len(values) else f"{text} ({len(v)} of {len(values)} seeds)"


def specialist_metrics(runs: list[Run], kind: str | None = None) -> list[dict]:
    """The specialists' metrics once per seed (every method of a seed from one kind of
    specialists re-evaluates the same ones): of the runs starting from `kind` (all when None)."""
    by_seed: dict[int, dict] = {}
    for r in sorted(runs, key=lambda r: (r.seed, METHOD_ORDER.index(r.method) if r.method in METHOD_ORDER else 99)):
        if kind is None or specialist_kind(r.method) == kind:
            by_seed.setdefault(r.seed, r.metrics["specialists"])
    return [by_seed[s] for s in sorted(by_seed)]


def specialist_runs(runs: list[Run]) -> dict[tuple[str, int], Run]:
    """(kind, seed) -> the run whose starting policies stand for that seed's specialists of that
    kind (every method of a seed and kind starts from the same ones), kinds in specialist_groups'
    order, then seeds: the first method of METHOD_ORDER, so an extraction variant (it starts from
    every policy of each set) before MOPDERL (it starts from its populations)."""
    chosen: dict[tuple[str, int], Run] = {}
    for r in sorted(runs, key=lambda r: METHOD_ORDER.index(r.method) if r.method in METHOD_ORDER else 99):
        if (kind := specialist_kind(r.method)) is not None:
            chosen.setdefault((kind, r.seed), r)
    return {key: chosen[key] for key in sorted(chosen, key=lambda ks: (specialist_rank(ks[0]), ks[1]))}


def specialist_rank(kind: str) -> tuple[int, str]:
    """Where specialists of `kind` sit in the report: SPECIALIST_ORDER, then specialists variants by name."""
    return (SPECIALIST_ORDER.index(kind), "") if kind in SPECIALIST_ORDER else (len(SPECIALIST_ORDER), kind)


def specialist_groups(runs: list[Run]) -> list[str]:
    """'specialists_pderl', 'specialists_td3': one per kind of specialists the runs start from."""
    kinds = {specialist_kind(r.method) for r in runs} - {None}
    return [f"specialists_{k}" for k in sorted(kinds, key=specialist_rank)]


TABLE_METRICS = (
    ("hypervolume", "Hypervolume (↑)"),
    ("sparsity", "Sparsity (↓)"),
    ("expected_utility", "Expected utility (↑)"),
    ("distinct_count", "Distinct points (↑)"),
)


def paper_table(runs: list[Run], env_id: str) -> str:
    """The paper's Table 1 layout (one row per env, a column group per metric) for every variant
    and the specialists: its two metrics (hypervolume, sparsity) plus two it does not report."""
    groups = [*methods_in(runs), *specialist_groups(runs)]
    header = ["Environment"] + [f"{title} {label(g)}" for _, title in TABLE_METRICS for g in groups]
    cells = [env_id]
    for key, _ in TABLE_METRICS:
        for g in groups:
            ms = (
                specialist_metrics(runs, g.removeprefix("specialists_"))
                if g.startswith("specialists_")
                else [r.metrics["front"] for r in runs if r.method == g]
            )
            cells.append(fmt_mean_sem([m[key] for m in ms]))
    return _md_table(header, [cells])


def _count(runs: list[Run], origin: str) -> str:
    return fmt_mean_sem([float((r.origin == origin).sum()) for r in runs])


def details_table(runs: list[Run]) -> str:
    """Per method: starting policies and members it made, HV ratio vs its specialists, HV
    fraction, PGMORL sparsity, cardinality, training-time HV, iterations and env frames."""
    header = [
        "Method",
        "seeds",
        "starting policies",
        "made by the method",
        "HV / HV(specialists)",
        "HV fraction of [ref, ideal] box",
        "sparsity (PGMORL)",
        "cardinality",
        "extraction/training-time HV",
        "iterations",
        "env frames (after specialists)",
    ]
    rows = []
    for v in methods_in(runs):
        rs = [r for r in runs if r.method == v]
        m = [r.metrics for r in rs]
        made = fmt_mean_sem([float((r.origin != "specialist").sum()) for r in rs])
        rows.append(
            [
                label(v),
                str(len(rs)),
                _count(rs, "specialist"),
                made,
                fmt_mean_sem([x["hv_ratio_vs_specialists"] for x in m]),
                fmt_mean_sem([x["front"]["hv_fraction"] for x in m]),
                fmt_mean_sem([x["front"]["sparsity_pgmorl"] for x in m]),
                fmt_mean_sem([x["front"]["cardinality"] for x in m]),
                fmt_mean_sem([x["extraction_hypervolume"] for x in m]),
                fmt_mean_sem([x["iterations"] for x in m]),
                frames_cell(m),
            ]
        )
    for g in specialist_groups(runs):
        kind = g.removeprefix("specialists_")
        sm = specialist_metrics(runs, kind)
        one_per_seed = [r for (k, _), r in specialist_runs(runs).items() if k == kind]
        # the specialists' HV fraction depends on which method's box it was measured in: not shown
        rows.append(
            [
                label(g),
                str(len(sm)),
                _count(one_per_seed, "specialist"),
                "0",
                "1",
                "",
                fmt_mean_sem([x["sparsity_pgmorl"] for x in sm]),
                fmt_mean_sem([x["cardinality"] for x in sm]),
                "",
                "0",
                "",
            ]
        )
    return _md_table(header, rows)


def frames_cell(metrics: list[dict]) -> str:
    """Env frames after the specialists; for imported specialists, plus the frames spent
    collecting their buffers (that path's sample cost, stage import_specialist)."""
    cell = fmt_mean_sem([x["env_samples_extraction"] for x in metrics])
    collected = [x.get("env_samples_collection", 0) for x in metrics]
    if any(collected):
        cell += f" + {fmt_mean_sem(collected)} collecting the imported specialists' buffers"
    return cell


def _md_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] * len(header)) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def frames_to_reach(
    runs: list[Run], a: str, b: str, fractions: tuple[float, ...] = (0.5, 0.9, 1.0)
) -> dict[float, list[float | None]]:
    """Per fraction f: for each seed with both methods, the cumulative env frames after which
    method a's population (re-evaluated hypervolume history) first reaches f x method b's final
    re-evaluated hypervolume; None where it never does."""
    by = {(r.method, r.seed): r for r in runs}
    seeds = sorted(s for (v, s) in by if v == a and (b, s) in by)
    out: dict[float, list[float | None]] = {f: [] for f in fractions}
    for s in seeds:
        ra, target = by[(a, s)], by[(b, s)].metrics["front"]["hypervolume"]
        hv, frames = ra.history["hypervolume"], ra.history["env_samples"]
        for f in fractions:
            hit = np.flatnonzero(hv >= f * target)
            out[f].append(float(frames[hit[0]]) if len(hit) else None)
    return out


def sample_efficiency_table(
    runs: list[Run],
    pairs: tuple[tuple[str, str], ...] = (
        ("mapex_pderl", "mopderl"),
        ("mopderl", "mapex_pderl"),
        ("mapex_posthoc_pderl", "mopderl"),
        ("mopderl", "mapex_posthoc_pderl"),
    ),
) -> str:
    """Env frames each method needs to reach 50%, 90% and 100% of the other's final re-evaluated
    hypervolume, from the same specialists (mean ± SEM over the seeds that reached it); '' when
    no pair was run."""
    rows = []
    present = {r.method for r in runs}
    for a, b in pairs:
        if a not in present or b not in present:
            continue
        reach = frames_to_reach(runs, a, b)
        cells = []
        for f, vals in reach.items():
            got = [v for v in vals if v is not None]
            if not got:
                cells.append("never")
            else:
                cell = fmt_mean_sem(got)
                cells.append(cell if len(got) == len(vals) else f"{cell} (reached in {len(got)} of {len(vals)} seeds)")
        rows.append([label(a), label(b), *cells])
    if not rows:
        return ""
    return _md_table(["method", "target: final HV of", "frames to 50%", "frames to 90%", "frames to 100%"], rows)


PROVENANCE_STAGES = tuple(PROVENANCE_FOLDERS)  # extract (or mopderl, morld), evaluate, score
PROVENANCE_COLUMNS = ("git commit", "torch", "numpy", "mujoco", "gymnasium", "mo-gymnasium", "device", "threads")


def provenance_cells(record: dict | None) -> tuple[str, ...]:
    """One provenance record (pipeline.core.provenance) as table cells; 'not recorded' where absent."""
    if not record:
        return ("not recorded",) * len(PROVENANCE_COLUMNS)
    versions = record.get("versions") or {}
    commit = record.get("git_commit")
    if commit is not None:  # a dirty checkout's results may come from uncommitted code
        commit = commit[:10] + {True: " (dirty)", False: ""}.get(record.get("git_dirty"), " (dirty: not recorded)")
    values = (
        commit,
        *(versions.get(lib) for lib in PROVENANCE_COLUMNS[1:6]),
        record.get("device"),
        record.get("torch_threads"),
    )
    return tuple("not recorded" if x is None else str(x) for x in values)


def _run_list(runs: list[Run]) -> str:
    """'MAPEX seeds 0, 1; warm-up only seed 2'."""
    parts = []
    for v in methods_in(runs):
        seeds = sorted(r.seed for r in runs if r.method == v)
        parts.append(f"{label(v)} seed{'s' if len(seeds) > 1 else ''} {', '.join(map(str, seeds))}")
    return "; ".join(parts)


def provenance_table(runs: list[Run]) -> str:
    """Per stage, what produced each run (variant x seed): runs with identical provenance share a
    row. 'extract' is the record of the stage that made the population (extract, mopderl or
    morld); 'not recorded' where a stage left no record (pipeline.reporting.runs.read_provenance)."""
    rows = []
    for stage in PROVENANCE_STAGES:
        groups: dict[tuple[str, ...], list[Run]] = {}
        for r in sorted(runs, key=lambda r: (r.seed, r.method)):
            groups.setdefault(provenance_cells((r.provenance or {}).get(stage)), []).append(r)
        rows += [[stage, _run_list(rs), *cells] for cells, rs in groups.items()]
    return _md_table(["stage", "runs", *PROVENANCE_COLUMNS], rows)
