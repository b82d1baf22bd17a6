"""The grid report (`mapex grid-report`): one report across the cells of a sweep, each a
workspace with its env and scored runs: Table 1 with a row per cell, the seeds behind each
cell, the weak-specialist warnings of each cell (by its own report params), the provenance of
every cell's runs, and fronts and hypervolume-vs-frames per cell; on request, paired verdicts
between a method of one cell and a method of another (`cross_verdicts`), by the per-cell
report's own verdict function and cost column."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from matplotlib.figure import Figure

from pipeline.params.report import ReportParams
from pipeline.reporting.cost import verdict_cost_table
from pipeline.reporting.figures import _band, _front_line, _panels, _shared_legend, step_values
from pipeline.reporting.presentation import colour, label
from pipeline.reporting.runs import Run, methods_in
from pipeline.reporting.specialists import weak_sentence, weak_specialists
from pipeline.reporting.tables import (
    PROVENANCE_COLUMNS,
    PROVENANCE_STAGES,
    TABLE_METRICS,
    _md_table,
    _run_list,
    fmt_mean_sem,
    provenance_cells,
    specialist_groups,
    specialist_metrics,
)
from pipeline.reporting.verdicts import Verdict, verdicts


@dataclass
class Cell:
    """One grid cell of a sweep: a workspace with its env and its scored runs."""

    name: str  # the sweep's cell name (env, or env.override_set)
    env_id: str
    runs: list[Run]
    names: list[str] | None = None  # objective names; None: "objective m"
    report: ReportParams = field(default_factory=ReportParams)  # the cell's `report` section (weak specialists)


@dataclass(frozen=True)
class Side:
    """One side of a verdict across cells: a method's runs in one cell."""

    cell: Cell
    method: str

    @property
    def name(self) -> str:
        """How the verdict names it: the method's label, then its cell in brackets."""
        return f"{label(self.method)} [{self.cell.name}]"

    def runs(self) -> list[Run]:
        """The cell's runs of the method, renamed after the side (so that two cells' runs of one
        method are two methods to the verdict function)."""
        return [replace(r, method=self.name) for r in self.cell.runs if r.method == self.method]

    def seeds(self) -> list[int]:
        return sorted(r.seed for r in self.cell.runs if r.method == self.method)


def left_out(a: Side, b: Side) -> str:
    """Which seeds a verdict across cells left out: those only one side has."""
    sa, sb = set(a.seeds()), set(b.seeds())
    only = [(s, a) for s in sorted(sa - sb)] + [(s, b) for s in sorted(sb - sa)]
    if not only:
        return "No seed left out: both sides have the same ones."
    return "Left out, unpaired: " + ", ".join(f"seed {s} ({side.name} only)" for s, side in only) + "."


def cross_verdicts(pairs: list[tuple[Side, Side]]) -> tuple[list[tuple[Verdict, str]], str]:
    """Per pair (a, b): did a beat, lose to or tie with b, paired by seed over the seeds both
    sides have, by the per-cell report's own function (pipeline.reporting.verdicts.verdicts:
    its rule, wording and numbers, with report.min_difference and report.noise_sems of a's
    cell; `mapex grid-report` refuses a pair whose cells disagree on them), with the seeds it
    left out; and the per-cell report's cost column beside them (verdict_cost_table; '' when
    no run recorded a cost). Each side's runs are its cell's, renamed `Side.name`, so each
    sentence names the cell of each method."""
    runs = {s.name: s.runs() for pair in pairs for s in pair}
    said = []
    for a, b in pairs:
        rule = a.cell.report
        (v,) = verdicts(runs[a.name] + runs[b.name], rule.min_difference, rule.noise_sems, [[a.name, b.name]])
        said.append((v, left_out(a, b)))
    return said, verdict_cost_table([v for v, _ in said], [r for rs in runs.values() for r in rs])


def cross_lines(pairs: list[tuple[Side, Side]]) -> list[str]:
    """The grid report's section of verdicts across cells (markdown lines; [] without pairs)."""
    if not pairs:
        return []
    said, costs = cross_verdicts(pairs)
    lines = [
        "## Verdicts across cells",
        "",
        "Each `--pair`: a method of one cell (named 'method [cell]') against a method of another, paired "
        "by seed over the seeds both have, by the rule and in the words of each cell's own report "
        "(pipeline/reporting/verdicts.py; report.min_difference and report.noise_sems, the same in both cells).",
        "",
        *(f"- {v.sentence} {out}" for v, out in said),
        "",
    ]
    if costs:
        lines += [
            "Each verdict beside what each side cost: the core-seconds of the stage that made each method's "
            "front in its cell (mean over its seeds; its evaluation episodes included, the specialists not), as "
            "in each cell's own report.",
            "",
            costs,
        ]
    return lines


def grid_table(cells: list[Cell]) -> str:
    """The paper's Table 1 across a grid: one row per cell (env), a column group per metric, a
    column per method (and the specialists of each kind) found in any cell; mean ± SEM over seeds."""
    all_runs = [r for c in cells for r in c.runs]
    groups = [*methods_in(all_runs), *specialist_groups(all_runs)]
    header = ["Environment"] + [f"{title} {label(g)}" for _, title in TABLE_METRICS for g in groups]
    rows = []
    for c in cells:
        cells_row = [c.name if c.name == c.env_id else f"{c.name} ({c.env_id})"]
        for key, _ in TABLE_METRICS:
            for g in groups:
                ms = (
                    specialist_metrics(c.runs, g.removeprefix("specialists_"))
                    if g.startswith("specialists_")
                    else [r.metrics["front"] for r in c.runs if r.method == g]
                )
                cells_row.append(fmt_mean_sem([m[key] for m in ms]) if ms else "")
        rows.append(cells_row)
    return _md_table(header, rows)


def grid_seeds_table(cells: list[Cell]) -> str:
    """Which seeds each cell's methods were scored on (a cell's mean ± SEM is over these)."""
    rows = []
    for c in cells:
        for v in methods_in(c.runs):
            seeds = sorted(r.seed for r in c.runs if r.method == v)
            rows.append([c.name, label(v), ", ".join(map(str, seeds))])
    return _md_table(["cell", "method", "seeds"], rows)


def grid_weak_lines(cells: list[Cell]) -> list[str]:
    """'- cell: Warning: ...' per weak specialist of each cell, by the cell's own report params."""
    lines = []
    for c in cells:
        names = c.names or [f"objective {m}" for m in range(c.runs[0].returns.shape[1])]
        weak = weak_specialists(c.runs, c.report.weak_specialist_fraction, c.report.weak_specialist_min_return)
        lines += [f"- {c.name}: {weak_sentence(w, names)}" for w in weak]
    return lines


def grid_provenance_table(cells: list[Cell]) -> str:
    """Per cell and stage record (extract = the population's producer, evaluate, score): what
    produced the runs; runs with identical provenance share a row."""
    rows = []
    for c in cells:
        for stage in PROVENANCE_STAGES:
            groups: dict[tuple[str, ...], list[Run]] = {}
            for r in sorted(c.runs, key=lambda r: (r.seed, r.method)):
                groups.setdefault(provenance_cells((r.provenance or {}).get(stage)), []).append(r)
            rows += [[c.name, stage, _run_list(rs), *cells] for cells, rs in groups.items()]
    return _md_table(["cell", "stage", "runs", *PROVENANCE_COLUMNS], rows)


def grid_fronts_figure(cells: list[Cell], width: float) -> Figure:
    """One panel per cell: every method's re-evaluated front, one line per seed (same colour).

    A cell with three or more objectives has no front line in two dimensions: its panel shows
    the front's points (non-dominated in all objectives) projected onto objectives 0 and 1, and
    says so; the per-cell report (stage `report`) has every pair and a 3-D view."""
    fig, _, axes = _panels(len(cells), width, 0.9)
    for ax, c in zip(axes, cells):
        m = max((r.returns.shape[1] for r in c.runs), default=2)
        names = c.names or [f"objective {k}" for k in range(m)]
        for v in methods_in(c.runs):
            for i, r in enumerate(sorted((r for r in c.runs if r.method == v), key=lambda r: r.seed)):
                kw = {"color": colour(v), "alpha": 0.8, "label": label(v) if i == 0 else None}
                if m > 2:
                    pts = r.returns[r.on_front]
                    ax.scatter(pts[:, 0], pts[:, 1], s=14, **kw)
                else:
                    _front_line(ax, r.returns[r.on_front, :2], lw=1.1, **kw)
        ax.set_title(c.name if m <= 2 else f"{c.name} (projection of {m} objectives)", fontsize="medium")
        ax.set_xlabel(names[0] if m > 2 else "objective 0")
        ax.set_ylabel(names[1] if m > 2 else "objective 1")
        ax.grid(alpha=0.3)
    _shared_legend(fig, axes)
    fig.suptitle("Re-evaluated fronts per cell (one line per seed)")
    return fig


def grid_history_figure(cells: list[Cell], width: float) -> Figure:
    """One panel per cell: re-evaluated hypervolume against cumulative env frames after the
    specialists, mean ± SEM over seeds per method."""
    fig, _, axes = _panels(len(cells), width, 0.8)
    for ax, c in zip(axes, cells):
        for v in methods_in(c.runs):
            rs = [r for r in c.runs if r.method == v]
            x = np.unique(np.concatenate([r.history["env_samples"] for r in rs]))
            curves = np.stack([step_values(r.history["env_samples"], r.history["hypervolume"], x) for r in rs])
            _band(ax, x, curves, colour(v), label(v), len(rs))
        ax.set_title(c.name, fontsize="medium")
        ax.set_xlabel("env frames after the specialists")
        ax.set_ylabel("hypervolume (re-evaluated)")
        ax.grid(alpha=0.3)
    _shared_legend(fig, axes)
    fig.suptitle("Hypervolume against env frames, per cell")
    return fig


def grid_markdown(cells: list[Cell], figures: dict[str, str], across: list[str] | None = None) -> str:
    """report.md across a grid: the verdicts across cells (`across`: cross_lines' section, if
    any pair was asked for), Table 1 (one row per cell), the seeds behind each cell, figures,
    provenance."""
    lines = [
        "# MAPEX grid report",
        "",
        f"- cells: {', '.join(c.name for c in cells)}",
        f"- methods: {', '.join(f'{label(v)} ({v})' for v in methods_in([r for c in cells for r in c.runs]))}",
        "",
        *(across or []),
        "## Table 1 across the grid",
        "",
        "Mean ± SEM over each cell's seeds of the re-evaluated final fronts (the definitions are those "
        "of each cell's own report, data/report/report.md in its workspace). Hypervolumes of different "
        "envs use each env's own reference point and are not comparable across rows. An empty cell: the "
        "method did not run there.",
        "",
        grid_table(cells),
        "## Seeds behind each cell",
        "",
        grid_seeds_table(cells),
        "## Weak specialists",
        "",
        "Specialists below the thresholds of their cell's `report` section on their own objective "
        "(report.weak_specialist_fraction, report.weak_specialist_min_return; each cell's own report "
        "has the table of every specialist's return).",
        "",
        *(grid_weak_lines(cells) or ["- None."]),
        "",
        "## Figures",
        "",
    ]
    for fname, caption in figures.items():
        lines += [f"![{caption}]({fname})", "", f"*{caption}*", ""]
    lines += ["## Provenance", "", grid_provenance_table(cells)]
    return "\n".join(lines)
