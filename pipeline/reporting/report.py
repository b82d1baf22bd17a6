"""The experiment report: figures and markdown tables from evaluated runs. No file paths here.

A `Run` is one (method, seed): the evaluate stage's re-evaluated returns plus the score
stage's metrics, front, hypervolume history and provenance. A method is an extraction variant
from one kind of specialists (mapex_pderl = the paper's MAPEX, mapex_posthoc_pderl =
MAPEX-PostHoc, mapex_td3 = MAPEX-TD3, warmup_only_<kind> = the ablation) or a baseline
(mopderl, morld); every method's population is scored by the same evaluator. Figures are matplotlib `Figure`s
rendered with Agg (no pyplot, no global backend state); tables and the verdict are markdown
strings computed from the numbers. Mean +- SEM across seeds as in the paper's Table 1.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from pipeline.evaluation.metrics import mean_sem

VARIANT_ORDER = ("mapex_pderl", "mapex_posthoc_pderl", "warmup_only_pderl", "mapex_td3", "mapex_posthoc_td3",
                 "warmup_only_td3", "mopderl", "morld")
LABELS = {
    "mapex_pderl": "MAPEX", "mapex_posthoc_pderl": "MAPEX-PostHoc", "warmup_only_pderl": "warm-up only (PDERL)",
    "mapex_td3": "MAPEX-TD3", "mapex_posthoc_td3": "MAPEX-TD3-PostHoc", "warmup_only_td3": "warm-up only (TD3)",
    "mopderl": "MOPDERL", "morld": "MORL/D",
    "specialists_pderl": "PDERL specialists only", "specialists_td3": "TD3 specialists only",
}
COLOURS = {"mapex_pderl": "tab:blue", "mapex_posthoc_pderl": "tab:cyan", "warmup_only_pderl": "tab:gray",
           "mapex_td3": "tab:green", "mapex_posthoc_td3": "tab:olive", "warmup_only_td3": "tab:orange",
           "mopderl": "tab:red", "morld": "tab:purple"}
# Comparisons the verdict section states when both methods of a pair were run: (a, b, what a is).
VERDICT_PAIRS = (
    ("mapex_pderl", "warmup_only_pderl", "the advantage-weighted phase (MAPEX)"),
    ("mapex_td3", "warmup_only_td3", "the advantage-weighted phase (MAPEX-TD3)"),
    ("mapex_posthoc_pderl", "mapex_pderl", "MAPEX-PostHoc (post-hoc critics)"),
    ("mapex_posthoc_td3", "mapex_td3", "MAPEX-TD3-PostHoc (post-hoc critics)"),
    ("mapex_pderl", "mapex_td3", "MAPEX (PDERL specialists)"),
    ("mapex_pderl", "mopderl", "MAPEX"),
    ("mapex_pderl", "morld", "MAPEX"),
)
SPECIALIST_COLOURS = ("tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:olive")  # by the specialist's objective


@dataclass
class Run:
    """One evaluated extraction run."""

    variant: str
    seed: int
    metrics: dict  # the score stage's metrics.json
    returns: np.ndarray  # (n, m) re-evaluated mean return of each member
    origin: np.ndarray  # (n,) "specialist" (a starting policy, from a specialist's policy set) or "child"
    iteration: np.ndarray  # (n,) iteration that made the member (0 for starting policies)
    on_front: np.ndarray  # (n,) bool, non-dominated among `returns`
    # the score stage's hypervolume.csv: iteration, env_samples, hypervolume_extract, hypervolume (each (T,))
    history: dict[str, np.ndarray]
    provenance: dict | None = None  # stage -> pipeline.core.provenance record or None (score's provenance.json)
    objective: np.ndarray | None = None  # (n,) the specialist a starting policy came from, -1 for a child

    def starting_counts(self) -> dict[int, int]:
        """Number of starting policies per specialist objective (1 each for TD3 specialists)."""
        spec = self.origin == "specialist"
        objectives = self.objective[spec] if self.objective is not None else np.full(int(spec.sum()), -1)
        keys, counts = np.unique(objectives, return_counts=True)
        return {int(k): int(c) for k, c in zip(keys, counts)}


def label(variant: str) -> str:
    return LABELS.get(variant, variant)


def specialist_kind(method: str) -> str | None:
    """The kind of specialists a method starts from: 'pderl' (MOPDERL's phase 2 too), 'td3', or
    None (MORL/D starts from nothing)."""
    if method == "mopderl" or method.endswith("_pderl"):
        return "pderl"
    if method.endswith("_td3"):
        return "td3"
    return None


def variants_in(runs: list[Run]) -> list[str]:
    """Variants present, the known ones first in their usual order."""
    present = {r.variant for r in runs}
    return [v for v in VARIANT_ORDER if v in present] + sorted(present - set(VARIANT_ORDER))


def _figure(width: float, height: float) -> Figure:
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _panels(n: int, width: float, aspect: float, share: bool = False) -> tuple[Figure, np.ndarray, np.ndarray]:
    """A figure of n panels, up to 3 a row, each `aspect` times as high as wide: (figure, the
    grid of axes, the first n axes); spare panels are hidden."""
    cols = min(n, 3)
    rows = -(-n // cols)
    fig = _figure(width, (width / cols) * aspect * rows)
    grid = fig.subplots(rows, cols, sharex=share, sharey=share, squeeze=False)
    for ax in grid.flat[n:]:
        ax.set_visible(False)
    return fig, grid, grid.flat[:n]


def _shared_legend(fig: Figure, axes) -> None:
    """One legend below the panels for every entry of `axes` (first label wins), instead of one
    legend per panel covering its points."""
    seen: dict[str, object] = {}
    for ax in axes:
        for handle, name in zip(*ax.get_legend_handles_labels()):
            seen.setdefault(name, handle)
    if seen:
        cols = 4 if max(map(len, seen)) <= 32 else 3 if max(map(len, seen)) <= 44 else 2
        fig.legend(list(seen.values()), list(seen), loc="outside lower center", ncols=min(cols, len(seen)), fontsize="small")


def _front_line(ax, points: np.ndarray, **kw) -> None:
    """Draw the attainment boundary of a 2-D maximisation front (points sorted by objective 0)."""
    if len(points) == 0:
        return
    p = points[np.argsort(points[:, 0])]
    ax.step(p[:, 0], p[:, 1], where="pre", **kw)


def _starting_policies(ax, run: Run, pts: np.ndarray) -> None:
    """The starting policies as stars, one colour per specialist (by its objective); smaller
    stars where a specialist gave a whole policy set."""
    spec = run.origin == "specialist"
    objective = run.objective if run.objective is not None else np.full(len(spec), -1)
    for k, n in run.starting_counts().items():
        sel = spec & (objective == k)
        name = "specialist" if k < 0 else f"specialist {k}"
        ax.scatter(pts[sel, 0], pts[sel, 1], marker="*", s=220 if n == 1 else 110,
                   color=SPECIALIST_COLOURS[k % len(SPECIALIST_COLOURS)] if k >= 0 else "tab:red", edgecolors="black",
                   lw=0.8, zorder=5, label=name if n == 1 else f"{name}: {n} starting policies")


def front_figure(runs: dict[str, Run], names: list[str], env_id: str, seed: int, width: float) -> Figure:
    """Fronts of one seed, one panel per variant: starting policies vs children coloured by iteration.

    Starting policies (every policy of each specialist's policy set; one per specialist for
    TD3) are stars, one colour per specialist. Non-dominated children are ringed, and the
    front's boundary joins the non-dominated members; each panel also shows the other
    variants' fronts dashed for comparison. Only objectives 0 and 1 are drawn.
    """
    variants = [v for v in variants_in(list(runs.values()))]
    fig, grid, axes = _panels(len(variants), width, 0.95 if len(variants) > 1 else 0.6, share=True)
    max_it = max(max(int(r.iteration.max()), 1) for r in runs.values())
    norm = Normalize(vmin=1, vmax=max_it)
    mappable = None
    for ax, v in zip(axes, variants):
        run = runs[v]
        pts, child = run.returns[:, :2], run.origin != "specialist"  # whatever the method made
        for other in variants:
            if other != v:
                _front_line(ax, runs[other].returns[runs[other].on_front, :2], color=COLOURS.get(other, "grey"),
                            ls="--", lw=1.2, alpha=0.8, label=f"{label(other)} front")
        _front_line(ax, pts[run.on_front], color="black", lw=1.2, label=f"{label(v)} front")
        if child.any():
            mappable = ax.scatter(pts[child, 0], pts[child, 1], c=np.maximum(run.iteration[child], 1), cmap="viridis", norm=norm,
                                  s=22, alpha=0.85, label="made by the method (colour: iteration)")
        nd = child & run.on_front
        if nd.any():
            ax.scatter(pts[nd, 0], pts[nd, 1], s=70, facecolors="none", edgecolors="black", lw=1.2,
                       label="non-dominated")
        _starting_policies(ax, run, pts)
        ax.set_title(label(v))
        ax.set_xlabel(names[0])
        ax.grid(alpha=0.3)
        if len(variants) == 1:
            ax.legend(fontsize="small", loc="best")
    if len(variants) > 1:
        _shared_legend(fig, axes)
    for row in grid:
        row[0].set_ylabel(names[1])
    if mappable is not None:
        cbar = fig.colorbar(mappable, ax=list(axes), label="iteration (MOPDERL: generation)", shrink=0.9)
        cbar.locator = MaxNLocator(integer=True)
        cbar.update_ticks()
    fig.suptitle(f"Re-evaluated fronts: {env_id}, seed {seed}")
    return fig


def step_values(x: np.ndarray, y: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """y of the last record with x <= grid (a step function); NaN before the first record."""
    order = np.argsort(x, kind="stable")
    x, y = np.asarray(x, float)[order], np.asarray(y, float)[order]
    idx = np.searchsorted(x, grid, side="right") - 1
    out = np.where(idx >= 0, y[np.clip(idx, 0, None)], np.nan)
    return out


def _band(ax, x: np.ndarray, curves: np.ndarray, colour: str, name: str, n: int, ls: str = "-") -> None:
    """Mean line (+- SEM band when several curves) of curves (n_seeds, len(x)), ignoring NaNs."""
    counts = np.sum(~np.isnan(curves), axis=0)
    with warnings.catch_warnings():  # columns with < 2 finite values warn; they are masked below
        warnings.simplefilter("ignore", RuntimeWarning)
        mean = np.nanmean(curves, axis=0)
        sd = np.nanstd(curves, axis=0, ddof=1)
    sem = np.where(counts > 1, sd / np.sqrt(np.maximum(counts, 1)), 0.0)
    ok = counts > 0
    ax.plot(x[ok], mean[ok], color=colour, lw=1.6, ls=ls, drawstyle="steps-post",
            label=f"{name} (mean of {n} seed{'s' if n > 1 else ''})")
    if n > 1:
        ax.fill_between(x[ok], (mean - sem)[ok], (mean + sem)[ok], step="post", color=colour,
                        alpha=0.25 if ls == "-" else 0.12, lw=0)


HISTORY_CURVES = (("hypervolume_extract", "-", "extraction-time"), ("hypervolume", "--", "re-evaluated"))


def history_figure(runs: list[Run], env_id: str, width: float) -> Figure:
    """Hypervolume of the population after each iteration vs iteration and vs cumulative
    extraction env samples, per variant: of the extraction-time returns (solid, the paper's
    curve) and of the same members' re-evaluated returns (dashed; its last point is the final
    front's hypervolume in the tables).

    Several seeds: mean +- SEM (samples: each seed's step curve on the union of sample counts).
    """
    fig = _figure(width, width * 0.4)
    ax_it, ax_s = fig.subplots(1, 2, sharey=True)
    for v in variants_in(runs):
        rs = [r for r in runs if r.variant == v]
        colour = COLOURS.get(v, "grey")
        its = np.unique(np.concatenate([r.history["iteration"] for r in rs]))
        grid = np.unique(np.concatenate([r.history["env_samples"] for r in rs]))
        for key, ls, kind in HISTORY_CURVES:
            name = f"{label(v)}, {kind}"
            _band(ax_it, its, np.stack([step_values(r.history["iteration"], r.history[key], its) for r in rs]),
                  colour, name, len(rs), ls)
            _band(ax_s, grid, np.stack([step_values(r.history["env_samples"], r.history[key], grid) for r in rs]),
                  colour, name, len(rs), ls)
    ax_it.set_xlabel("iteration")
    ax_it.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax_s.set_xlabel("env frames after the specialists")
    ax_it.set_ylabel("hypervolume")
    for ax in (ax_it, ax_s):
        ax.grid(alpha=0.3)
    _shared_legend(fig, [ax_it])
    fig.suptitle(f"Hypervolume of the population as each method runs: {env_id}")
    return fig


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
    for r in sorted(runs, key=lambda r: (r.seed, VARIANT_ORDER.index(r.variant) if r.variant in VARIANT_ORDER else 99)):
        if kind is None or specialist_kind(r.variant) == kind:
            by_seed.setdefault(r.seed, r.metrics["specialists"])
    return [by_seed[s] for s in sorted(by_seed)]


def specialist_groups(runs: list[Run]) -> list[str]:
    """'specialists_pderl', 'specialists_td3': one per kind of specialists the runs start from."""
    kinds = {specialist_kind(r.variant) for r in runs} - {None}
    return [f"specialists_{k}" for k in ("pderl", "td3") if k in kinds]


TABLE_METRICS = (("hypervolume", "Hypervolume (↑)"), ("sparsity", "Sparsity (↓)"),
                 ("expected_utility", "Expected utility (↑)"), ("distinct_count", "Distinct points (↑)"))


def paper_table(runs: list[Run], env_id: str) -> str:
    """The paper's Table 1 layout (one row per env, a column group per metric) for every variant
    and the specialists: its two metrics (hypervolume, sparsity) plus two it does not report."""
    groups = [*variants_in(runs), *specialist_groups(runs)]
    header = ["Environment"] + [f"{title} {label(g)}" for _, title in TABLE_METRICS for g in groups]
    cells = [env_id]
    for key, _ in TABLE_METRICS:
        for g in groups:
            ms = (specialist_metrics(runs, g.removeprefix("specialists_")) if g.startswith("specialists_")
                  else [r.metrics["front"] for r in runs if r.variant == g])
            cells.append(fmt_mean_sem([m[key] for m in ms]))
    return _md_table(header, [cells])


def _count(runs: list[Run], origin: str) -> str:
    return fmt_mean_sem([float((r.origin == origin).sum()) for r in runs])


def details_table(runs: list[Run]) -> str:
    """Per method: starting policies and members it made, HV ratio vs its specialists, HV
    fraction, PGMORL sparsity, cardinality, training-time HV, iterations and env frames."""
    header = ["Method", "seeds", "starting policies", "made by the method", "HV / HV(specialists)", "HV fraction of [ref, ideal] box",
              "sparsity (PGMORL)", "cardinality", "extraction/training-time HV", "iterations", "env frames (after specialists)"]
    rows = []
    for v in variants_in(runs):
        rs = [r for r in runs if r.variant == v]
        m = [r.metrics for r in rs]
        made = fmt_mean_sem([float((r.origin != "specialist").sum()) for r in rs])
        rows.append([label(v), str(len(rs)), _count(rs, "specialist"), made,
                     fmt_mean_sem([x["hv_ratio_vs_specialists"] for x in m]),
                     fmt_mean_sem([x["front"]["hv_fraction"] for x in m]),
                     fmt_mean_sem([x["front"]["sparsity_pgmorl"] for x in m]),
                     fmt_mean_sem([x["front"]["cardinality"] for x in m]),
                     fmt_mean_sem([x["extraction_hypervolume"] for x in m]),
                     fmt_mean_sem([x["iterations"] for x in m]),
                     fmt_mean_sem([x["env_samples_extraction"] for x in m])])
    for g in specialist_groups(runs):
        kind = g.removeprefix("specialists_")
        sm = specialist_metrics(runs, kind)
        # every method of a seed from this kind starts from the same policies
        # (the extraction runs first: they start from every policy of the sets, MOPDERL from the populations)
        ordered = sorted(runs, key=lambda r: VARIANT_ORDER.index(r.variant) if r.variant in VARIANT_ORDER else 99, reverse=True)
        one_per_seed = list({r.seed: r for r in ordered if specialist_kind(r.variant) == kind}.values())
        # the specialists' HV fraction depends on which method's box it was measured in: not shown
        rows.append([label(g), str(len(sm)), _count(one_per_seed, "specialist"), "0", "1", "",
                     fmt_mean_sem([x["sparsity_pgmorl"] for x in sm]), fmt_mean_sem([x["cardinality"] for x in sm]), "", "0", ""])
    return _md_table(header, rows)


def _md_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join(["---"] * len(header)) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


@dataclass(frozen=True)
class Verdict:
    outcome: str  # "beat", "lost", "tied" or "unknown" (no seed has both variants)
    sentence: str


def verdict_outcome(d: np.ndarray, warm: np.ndarray, min_difference: float, noise_sems: float) -> str:
    """'beat', 'lost' or 'tied' from the paired per-seed differences d = MAPEX - warm-up only (n,).

    n >= 2: 'beat' when mean(d) > noise_sems * SEM(d) and MAPEX is higher in more than half of
    the seeds; 'lost' the mirror image; otherwise 'tied' (inside the seed noise). n = 1: no
    noise estimate, so 'beat'/'lost' need |d| > min_difference * |warm| (warm-up only's
    hypervolume), otherwise 'tied'; with warm = 0 any nonzero difference counts.
    """
    n = len(d)
    if n == 1:
        big = abs(d[0]) > min_difference * abs(warm[0])
        return "beat" if big and d[0] > 0 else "lost" if big and d[0] < 0 else "tied"
    dm, dsem = mean_sem(d)
    beyond = abs(dm) > noise_sems * dsem
    if beyond and dm > 0 and (d > 0).sum() > n / 2:
        return "beat"
    if beyond and dm < 0 and (d < 0).sum() > n / 2:
        return "lost"
    return "tied"


def _percent(diff: float, base: float) -> str:
    return f"{diff / abs(base) * 100:+.1f}%" if base != 0 else "n/a"


def hv_verdict(runs: list[Run], min_difference: float = 0.05, noise_sems: float = 2.0, a: str = "mapex_td3",
               b: str = "warmup_only_td3", what: str | None = None) -> Verdict:
    """Did method `a` beat method `b` on re-evaluated hypervolume? (Default: MAPEX-TD3 vs its
    warm-up only ablation, i.e. did the advantage-weighted phase help.)

    Paired over the seeds that have both methods; the rule is `verdict_outcome`'s, and the
    sentence states it with the numbers: each method's mean ± SEM over those seeds, the mean
    paired difference ± its SEM (also relative to b's mean), and in how many seeds a was higher
    and lower. With one seed it says there is no noise estimate. `what` names a in the sentence.
    """
    la, lb = label(a), label(b)
    what = what or next((w for x, y, w in VERDICT_PAIRS if (x, y) == (a, b)), la)
    hv = {(r.variant, r.seed): r.metrics["front"]["hypervolume"] for r in runs}
    seeds = sorted(s for (v, s) in hv if v == a and (b, s) in hv)
    if not seeds:
        return Verdict("unknown", f"Cannot say whether {what} beat {lb} on hypervolume: no seed has evaluated "
                                  f"results for both.")
    x = np.array([hv[(a, s)] for s in seeds], dtype=float)
    y = np.array([hv[(b, s)] for s in seeds], dtype=float)
    d = x - y
    n = len(seeds)
    outcome = verdict_outcome(d, y, min_difference, noise_sems)
    iters = max(int(r.metrics["iterations"]) for r in runs if r.variant in (a, b))
    tally = f"{la} was higher in {int((d > 0).sum())} of {n} seed(s), lower in {int((d < 0).sum())}"
    if n > 1:
        (am, asem), (bm, bsem), (dm, dsem) = mean_sem(x), mean_sem(y), mean_sem(d)
        z = f"{abs(dm) / dsem:.1f} SEM from zero" if dsem > 0 else "every seed's difference the same"
        numbers = (f"Mean ± SEM over seeds {', '.join(map(str, seeds))}: {la} {fmt_num(am)} ± {fmt_num(asem)}, "
                   f"{lb} {fmt_num(bm)} ± {fmt_num(bsem)}. Paired by seed, {la} - {lb} = "
                   f"{fmt_num(dm)} ± {fmt_num(dsem)} (SEM; {_percent(dm, bm)} of {lb}'s mean, {z}); {tally}.")
        rule = (f"Rule: 'beat' or 'lost to' needs the mean paired difference beyond {noise_sems:g} SEM of the "
                f"paired differences (report.noise_sems) and the same sign in more than half of the seeds; "
                f"otherwise 'tied with': inside the seed noise.")
    else:
        numbers = (f"One seed only ({seeds[0]}), so no estimate of seed noise: {la} {fmt_num(float(x[0]))}, "
                   f"{lb} {fmt_num(float(y[0]))}, difference {fmt_num(float(d[0]))} "
                   f"({_percent(float(d[0]), float(y[0]))}); {tally}.")
        rule = (f"Rule: with one seed, a difference within ±{min_difference * 100:g}% of {lb}'s hypervolume "
                f"(report.min_difference) counts as a tie.")
    verb = {"beat": "beat", "lost": "lost to", "tied": "tied with"}[outcome]
    text = (f"At this scale ({n} seed{'s' if n > 1 else ''}, up to {iters} iterations), {what} {verb} {lb} on "
            f"re-evaluated hypervolume. {numbers} {rule}")
    return Verdict(outcome, text)


def verdicts(runs: list[Run], min_difference: float = 0.05, noise_sems: float = 2.0) -> list[Verdict]:
    """One verdict per pair of VERDICT_PAIRS whose two methods were both run (paired by seed)."""
    present = {r.variant for r in runs}
    return [hv_verdict(runs, min_difference, noise_sems, a, b, what) for a, b, what in VERDICT_PAIRS
            if a in present and b in present]


def frames_to_reach(runs: list[Run], a: str, b: str, fractions: tuple[float, ...] = (0.5, 0.9, 1.0)) -> dict[float, list[float | None]]:
    """Per fraction f: for each seed with both methods, the cumulative env frames after which
    method a's population (re-evaluated hypervolume history) first reaches f x method b's final
    re-evaluated hypervolume; None where it never does."""
    by = {(r.variant, r.seed): r for r in runs}
    seeds = sorted(s for (v, s) in by if v == a and (b, s) in by)
    out: dict[float, list[float | None]] = {f: [] for f in fractions}
    for s in seeds:
        ra, target = by[(a, s)], by[(b, s)].metrics["front"]["hypervolume"]
        hv, frames = ra.history["hypervolume"], ra.history["env_samples"]
        for f in fractions:
            hit = np.flatnonzero(hv >= f * target)
            out[f].append(float(frames[hit[0]]) if len(hit) else None)
    return out


def sample_efficiency_table(runs: list[Run], pairs: tuple[tuple[str, str], ...] = (("mapex_pderl", "mopderl"),
                            ("mopderl", "mapex_pderl"), ("mapex_posthoc_pderl", "mopderl"), ("mopderl", "mapex_posthoc_pderl"))) -> str:
    """Env frames each method needs to reach 50%, 90% and 100% of the other's final re-evaluated
    hypervolume, from the same specialists (mean ± SEM over the seeds that reached it); '' when
    no pair was run."""
    rows = []
    present = {r.variant for r in runs}
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


PROVENANCE_STAGES = ("extract", "evaluate", "score")
PROVENANCE_COLUMNS = ("git commit", "torch", "numpy", "mujoco", "gymnasium", "mo-gymnasium", "device", "threads")


def provenance_cells(record: dict | None) -> tuple[str, ...]:
    """One provenance record (pipeline.core.provenance) as table cells; 'not recorded' where absent."""
    if not record:
        return ("not recorded",) * len(PROVENANCE_COLUMNS)
    versions = record.get("versions") or {}
    commit = record.get("git_commit")
    if commit is not None:  # a dirty checkout's results may come from uncommitted code
        commit = commit[:10] + {True: " (dirty)", False: ""}.get(record.get("git_dirty"), " (dirty: not recorded)")
    values = (commit, *(versions.get(lib) for lib in PROVENANCE_COLUMNS[1:6]), record.get("device"), record.get("torch_threads"))
    return tuple("not recorded" if x is None else str(x) for x in values)


def _run_list(runs: list[Run]) -> str:
    """'MAPEX seeds 0, 1; warm-up only seed 2'."""
    parts = []
    for v in variants_in(runs):
        seeds = sorted(r.seed for r in runs if r.variant == v)
        parts.append(f"{label(v)} seed{'s' if len(seeds) > 1 else ''} {', '.join(map(str, seeds))}")
    return "; ".join(parts)


def provenance_table(runs: list[Run]) -> str:
    """Per stage, what produced each run (variant x seed): runs with identical provenance share a
    row. 'extract' is the population's record (population.pt meta['provenance'])."""
    rows = []
    for stage in PROVENANCE_STAGES:
        groups: dict[tuple[str, ...], list[Run]] = {}
        for r in sorted(runs, key=lambda r: (r.seed, r.variant)):
            groups.setdefault(provenance_cells((r.provenance or {}).get(stage)), []).append(r)
        rows += [[stage, _run_list(rs), *cells] for cells, rs in groups.items()]
    return _md_table(["stage", "runs", *PROVENANCE_COLUMNS], rows)


def report_markdown(
    runs: list[Run],
    env_id: str,
    names: list[str],
    figures: dict[str, str],
    context: dict[str, str],
    min_difference: float = 0.05,
    noise_sems: float = 2.0,
) -> str:
    """The whole report.md: verdict, tables, figures (name -> caption, files beside report.md),
    provenance, definitions."""
    seeds = sorted({r.seed for r in runs})
    ref = runs[0].metrics.get("reference_point")
    said = verdicts(runs, min_difference, noise_sems)
    lines = [
        f"# MAPEX report: {env_id}",
        "",
        f"- methods: {', '.join(f'{label(v)} ({v})' for v in variants_in(runs))}",
        f"- seeds: {', '.join(map(str, seeds))}",
        f"- objectives: {', '.join(f'{i}: {n}' for i, n in enumerate(names))}",
        f"- hypervolume reference point: {ref}",
        *(f"- {k}: {v}" for k, v in context.items()),
        "",
        "## Verdicts",
        "",
        *([f"- {v.sentence}" for v in said] or ["- No pair of comparable methods was run (see report.py VERDICT_PAIRS)."]),
        "",
        "## Metrics of the re-evaluated final fronts",
        "",
        f"Mean ± SEM across seeds{' (one seed: no SEM)' if len(seeds) < 2 else ''}. The layout of the paper's "
        "Table 1 (one row per environment, a column group per metric); the paper reports hypervolume and "
        "sparsity only, expected utility and distinct points are added here. 'specialists only' is the front "
        "of the specialists alone: every starting policy (all of each specialist's policy set, one policy for a "
        "TD3 specialist), before any child. 'starting policies' and 'made by the method' count the population's "
        "members (MAPEX: its children; MOPDERL: the phase-2 individuals that entered its archive; MORL/D: its policies).",
        "",
        paper_table(runs, env_id),
        details_table(runs),
        *(["## Sample efficiency: extraction vs distillation from the same specialists", "",
           "Cumulative env frames after the specialists (MAPEX: its evaluation episodes; MOPDERL: every "
           "phase-2 frame) until a method's population first reaches a fraction of the other's final "
           "re-evaluated hypervolume, on the re-evaluated hypervolume history.", "", eff]
          if (eff := sample_efficiency_table(runs)) else []),
        "## Figures",
        "",
    ]
    for fname, caption in figures.items():
        lines += [f"![{caption}]({fname})", "", f"*{caption}*", ""]
    lines += [
        "## Provenance",
        "",
        "What produced each run: the population (extract), its re-evaluation (evaluate) and the "
        "scoring (score). Runs with identical provenance share a row. Results are bitwise "
        "reproducible only between runs that agree on every column (README, Reproducibility).",
        "",
        provenance_table(runs),
        "## Definitions",
        "",
        "- Every member of the final population was re-evaluated on fresh episode seeds (not those "
        "used during extraction); the front is the non-dominated set of the re-evaluated mean returns.",
        "- Hypervolume: exact (pymoo) above the fixed reference point. HV fraction: hypervolume over "
        "the volume of the box between the reference point and the ideal point (per-objective maximum "
        "of the re-evaluated population), the same box for the front and for the specialists.",
        "- Sparsity (the paper's Table 1): mean Euclidean distance between neighbouring points of the "
        "front sorted along objective 0. Raw return units. Sparsity (PGMORL): sort the front along each "
        "objective separately, sum the squared neighbour gaps over the objectives, divide by n - 1; "
        "squared units, not comparable with the paper's.",
        "- Expected utility: mean over evenly spread weight vectors w of max over the front of w · J, on "
        "raw (unnormalised) returns as morl-baselines does; the larger-scale objective weighs more.",
        "- Distinct points: non-dominated points left after merging points closer than the tolerance "
        "(a fraction of the [reference, ideal] box side, objectives normalised to it).",
        "- Extraction-time HV: hypervolume of the front of the returns measured during extraction "
        "(fewer episodes, each member evaluated once); above the re-evaluated HV it shows selection optimism.",
        "- Hypervolume history: after each iteration, the hypervolume of every member made so far, on "
        "extraction-time returns (what the paper plots) and on the same members' re-evaluated returns.",
        "",
    ]
    return "\n".join(lines)


# ---------------------------------------------------------------- across a grid of envs (mapex grid-report)


@dataclass
class Cell:
    """One grid cell of a sweep: a workspace with its env and its scored runs."""

    name: str  # the sweep's cell name (env, or env.override_set)
    env_id: str
    runs: list[Run]


def grid_table(cells: list[Cell]) -> str:
    """The paper's Table 1 across a grid: one row per cell (env), a column group per metric, a
    column per method (and the specialists of each kind) found in any cell; mean ± SEM over seeds."""
    all_runs = [r for c in cells for r in c.runs]
    groups = [*variants_in(all_runs), *specialist_groups(all_runs)]
    header = ["Environment"] + [f"{title} {label(g)}" for _, title in TABLE_METRICS for g in groups]
    rows = []
    for c in cells:
        cells_row = [c.name if c.name == c.env_id else f"{c.name} ({c.env_id})"]
        for key, _ in TABLE_METRICS:
            for g in groups:
                ms = (specialist_metrics(c.runs, g.removeprefix("specialists_")) if g.startswith("specialists_")
                      else [r.metrics["front"] for r in c.runs if r.variant == g])
                cells_row.append(fmt_mean_sem([m[key] for m in ms]) if ms else "")
        rows.append(cells_row)
    return _md_table(header, rows)


def grid_seeds_table(cells: list[Cell]) -> str:
    """Which seeds each cell's methods were scored on (a cell's mean ± SEM is over these)."""
    rows = []
    for c in cells:
        for v in variants_in(c.runs):
            seeds = sorted(r.seed for r in c.runs if r.variant == v)
            rows.append([c.name, label(v), ", ".join(map(str, seeds))])
    return _md_table(["cell", "method", "seeds"], rows)


def grid_provenance_table(cells: list[Cell]) -> str:
    """Per cell and stage record (extract = the population's producer, evaluate, score): what
    produced the runs; runs with identical provenance share a row."""
    rows = []
    for c in cells:
        for stage in PROVENANCE_STAGES:
            groups: dict[tuple[str, ...], list[Run]] = {}
            for r in sorted(c.runs, key=lambda r: (r.seed, r.variant)):
                groups.setdefault(provenance_cells((r.provenance or {}).get(stage)), []).append(r)
            rows += [[c.name, stage, _run_list(rs), *cells] for cells, rs in groups.items()]
    return _md_table(["cell", "stage", "runs", *PROVENANCE_COLUMNS], rows)


def grid_fronts_figure(cells: list[Cell], width: float) -> Figure:
    """One panel per cell: every method's re-evaluated front, one line per seed (same colour)."""
    fig, _, axes = _panels(len(cells), width, 0.9)
    for ax, c in zip(axes, cells):
        for v in variants_in(c.runs):
            for i, r in enumerate(sorted((r for r in c.runs if r.variant == v), key=lambda r: r.seed)):
                _front_line(ax, r.returns[r.on_front, :2], color=COLOURS.get(v, "grey"), lw=1.1, alpha=0.8,
                            label=label(v) if i == 0 else None)
        ax.set_title(c.name, fontsize="medium")
        ax.set_xlabel("objective 0")
        ax.set_ylabel("objective 1")
        ax.grid(alpha=0.3)
    _shared_legend(fig, axes)
    fig.suptitle("Re-evaluated fronts per cell (one line per seed)")
    return fig


def grid_history_figure(cells: list[Cell], width: float) -> Figure:
    """One panel per cell: re-evaluated hypervolume against cumulative env frames after the
    specialists, mean ± SEM over seeds per method."""
    fig, _, axes = _panels(len(cells), width, 0.8)
    for ax, c in zip(axes, cells):
        for v in variants_in(c.runs):
            rs = [r for r in c.runs if r.variant == v]
            x = np.unique(np.concatenate([r.history["env_samples"] for r in rs]))
            curves = np.stack([step_values(r.history["env_samples"], r.history["hypervolume"], x) for r in rs])
            _band(ax, x, curves, COLOURS.get(v, "grey"), label(v), len(rs))
        ax.set_title(c.name, fontsize="medium")
        ax.set_xlabel("env frames after the specialists")
        ax.set_ylabel("hypervolume (re-evaluated)")
        ax.grid(alpha=0.3)
    _shared_legend(fig, axes)
    fig.suptitle("Hypervolume against env frames, per cell")
    return fig


def grid_markdown(cells: list[Cell], figures: dict[str, str]) -> str:
    """report.md across a grid: Table 1 (one row per cell), the seeds behind each cell, figures, provenance."""
    lines = [
        "# MAPEX grid report",
        "",
        f"- cells: {', '.join(c.name for c in cells)}",
        f"- methods: {', '.join(f'{label(v)} ({v})' for v in variants_in([r for c in cells for r in c.runs]))}",
        "",
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
        "## Figures",
        "",
    ]
    for fname, caption in figures.items():
        lines += [f"![{caption}]({fname})", "", f"*{caption}*", ""]
    lines += ["## Provenance", "", grid_provenance_table(cells)]
    return "\n".join(lines)
