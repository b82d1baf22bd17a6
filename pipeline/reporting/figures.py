"""The report's figures: the fronts of one seed (one panel per method, starting policies apart
from what each method made; with 3 or more objectives, every pair of objectives and a 3-D view
per method) and the hypervolume history (vs iteration and vs env frames), with the panel,
legend, front-line and mean +- SEM band helpers the grid report's figures share.
Matplotlib `Figure`s rendered with Agg (no pyplot, no global backend state)."""

from __future__ import annotations

import itertools
import warnings

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from pipeline.core.pareto import pareto_mask
from pipeline.reporting.presentation import colour, label
from pipeline.reporting.runs import Run, methods_in

SPECIALIST_COLOURS = ("tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:olive")  # by the specialist's objective


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
        fig.legend(
            list(seen.values()), list(seen), loc="outside lower center", ncols=min(cols, len(seen)), fontsize="small"
        )


def _front_line(ax, points: np.ndarray, **kw) -> None:
    """Draw the attainment boundary of a 2-D maximisation front (points sorted by objective 0)."""
    if len(points) == 0:
        return
    p = points[np.argsort(points[:, 0])]
    ax.step(p[:, 0], p[:, 1], where="pre", **kw)


def _starting_policies(ax, run: Run, pts: np.ndarray, scale: float = 1.0) -> None:
    """The starting policies as stars, one colour per specialist (by its objective); smaller
    stars where a specialist gave a whole policy set. `pts` (n, 2) or, on a 3-D axes, (n, 3):
    the coordinates drawn of every member; `scale` multiplies the stars' area."""
    spec = run.origin == "specialist"
    objective = run.objective if run.objective is not None else np.full(len(spec), -1)
    for k, n in run.starting_counts().items():
        sel = spec & (objective == k)
        name = "specialist" if k < 0 else f"specialist {k}"
        ax.scatter(
            *pts[sel].T,
            marker="*",
            s=(220 if n == 1 else 110) * scale,
            color=SPECIALIST_COLOURS[k % len(SPECIALIST_COLOURS)] if k >= 0 else "tab:red",
            edgecolors="black",
            lw=0.8,
            zorder=5,
            label=name if n == 1 else f"{name}: {n} starting policies",
        )


def front_figure(runs: dict[str, Run], names: list[str], env_id: str, seed: int, width: float) -> Figure:
    """Fronts of one seed (`runs`: method -> its run of that seed), starting policies apart from
    what each method made. Two objectives: one panel per method (`front_figure_2d`); three or
    more: every pairwise projection and a 3-D view per method (`front_figure_nd`)."""
    m = next(iter(runs.values())).returns.shape[1]
    if m < 3:
        return front_figure_2d(runs, names, env_id, seed, width)
    return front_figure_nd(runs, names, env_id, seed, width)


def front_caption(runs: list[Run], seed: int) -> str:
    """The caption of `front_figure` for the runs of one seed."""
    methods = " vs ".join(label(v) for v in methods_in(runs))
    m = runs[0].returns.shape[1]
    if m < 3:
        return (
            f"Seed {seed}: re-evaluated returns of every member, starting policies "
            f"as stars (one colour per specialist), what each method made coloured by iteration; "
            f"{methods} side by side."
        )
    first3 = "" if m == 3 else " (the first three objectives)"
    return (
        f"Seed {seed}: re-evaluated returns of every member, one row of panels per method ({methods}): "
        f"each pair of the {m} objectives, then a 3-D view{first3}. Starting policies as stars (one colour "
        f"per specialist), what each method made coloured by iteration; ringed: the members non-dominated "
        f"in all {m} objectives (in a projection they may look dominated)."
    )


def front_figure_2d(runs: dict[str, Run], names: list[str], env_id: str, seed: int, width: float) -> Figure:
    """Fronts of one seed, one panel per variant: starting policies vs children coloured by iteration.

    Starting policies (every policy of each specialist's policy set; one per specialist for
    TD3) are stars, one colour per specialist. Non-dominated children are ringed, and the
    front's boundary joins the non-dominated members; each panel also shows the other
    variants' fronts dashed for comparison. Only objectives 0 and 1 are drawn.
    """
    variants = [v for v in methods_in(list(runs.values()))]
    fig, grid, axes = _panels(len(variants), width, 0.95 if len(variants) > 1 else 0.6, share=True)
    max_it = max(max(int(r.iteration.max()), 1) for r in runs.values())
    norm = Normalize(vmin=1, vmax=max_it)
    mappable = None
    for ax, v in zip(axes, variants):
        run = runs[v]
        pts, child = run.returns[:, :2], run.origin != "specialist"  # whatever the method made
        for other in variants:
            if other != v:
                _front_line(
                    ax,
                    runs[other].returns[runs[other].on_front, :2],
                    color=colour(other),
                    ls="--",
                    lw=1.2,
                    alpha=0.8,
                    label=f"{label(other)} front",
                )
        _front_line(ax, pts[run.on_front], color="black", lw=1.2, label=f"{label(v)} front")
        if child.any():
            mappable = ax.scatter(
                pts[child, 0],
                pts[child, 1],
                c=np.maximum(run.iteration[child], 1),
                cmap="viridis",
                norm=norm,
                s=22,
                alpha=0.85,
                label="made by the method (colour: iteration)",
            )
        nd = child & run.on_front
        if nd.any():
            ax.scatter(
                pts[nd, 0], pts[nd, 1], s=70, facecolors="none", edgecolors="black", lw=1.2, label="non-dominated"
            )
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


ND_COLUMNS = 3  # projections per row of a method's block in the m >= 3 front figure (the 3-D view beside them)
ND_STAR_SCALE = 0.5  # the stars' area there, relative to the one-panel-per-method figure's
ND_3D_WIDTH = (1.4, 2.0)  # the 3-D view's width relative to a projection's, beside one row of them, beside more


def _nd_members(ax, run: Run, pts: np.ndarray, nd: np.ndarray, norm: Normalize):
    """One panel of the m >= 3 figure: children coloured by iteration, the members non-dominated
    in all objectives (`nd`) ringed, the starting policies as stars; `pts` (n, 2) or (n, 3) are
    the coordinates drawn. Returns the children's scatter (None without children)."""
    child = run.origin != "specialist"
    made = None
    if child.any():
        made = ax.scatter(
            *pts[child].T,
            c=np.maximum(run.iteration[child], 1),
            cmap="viridis",
            norm=norm,
            s=14,
            alpha=0.85,
            label="made by the method (colour: iteration)",
        )
    if nd.any():
        # around a star the ring is drawn larger, so that it encloses it
        ax.scatter(
            *pts[nd].T,
            s=np.where(child[nd], 45, 150),
            facecolors="none",
            edgecolors="black",
            lw=1.0,
            zorder=6,
            label=f"non-dominated (all {run.returns.shape[1]} objectives)",
        )
    _starting_policies(ax, run, pts, ND_STAR_SCALE)
    return made


def _limits(values: np.ndarray) -> tuple[float, float]:
    """Axis limits holding `values` with a 5% margin (a unit margin when they are all equal)."""
    lo, hi = float(np.min(values)), float(np.max(values))
    pad = 0.05 * (hi - lo) if hi > lo else 1.0
    return lo - pad, hi + pad


def _nd_foot(foot, axes: list, mappable) -> float:
    """Below the blocks of the m >= 3 front figure: one legend for every panel (first label
    wins), then the iteration colour bar. Returns the height (inches) the foot needs."""
    seen: dict[str, object] = {}
    for ax in axes:
        for handle, name in zip(*ax.get_legend_handles_labels()):
            seen.setdefault(name, handle)
    longest = max(map(len, seen), default=0)
    cols = min(4 if longest <= 32 else 3 if longest <= 44 else 2, max(len(seen), 1))
    legend_height = 0.19 * -(-len(seen) // cols) + 0.12
    bar_height = 0.6 if mappable is not None else 0.0
    height = legend_height + bar_height
    if seen:
        foot.legend(list(seen.values()), list(seen), loc="upper center", ncols=cols, fontsize="small")
    if mappable is not None:
        cax = foot.add_axes((0.3, 0.42 / height, 0.4, 0.12 / height))
        cbar = foot.colorbar(mappable, cax=cax, orientation="horizontal")
        cbar.set_label("iteration (MOPDERL: generation)", fontsize="small")
        cbar.locator = MaxNLocator(integer=True)
        cbar.update_ticks()
    return height


def front_figure_nd(runs: dict[str, Run], names: list[str], env_id: str, seed: int, width: float) -> Figure:
    """Fronts of one seed with m >= 3 objectives: per method, a block of panels, one per pair of
    objectives (i, j), i < j (x: objective i, y: objective j), up to ND_COLUMNS a row, and beside
    them a 3-D view of objectives 0, 1, 2 as high as the block.

    Each panel shows every member: children coloured by iteration, starting policies as stars
    (one colour per specialist), and rings around the members non-dominated in all m objectives
    (`pareto_mask` of the run's returns; a ringed point may look dominated in a projection).
    The panels of one pair (and the 3-D views) have the same limits in every method's block.
    Axes are labelled "<method>: objectives i, j" and "<method>: 3-D" (`Axes.get_label`).
    """
    variants = methods_in(list(runs.values()))
    m = next(iter(runs.values())).returns.shape[1]
    pairs = list(itertools.combinations(range(m), 2))
    cols = min(len(pairs), ND_COLUMNS)
    rows = -(-len(pairs) // cols)
    width_3d = ND_3D_WIDTH[0] if rows == 1 else ND_3D_WIDTH[1]
    panel = width / (cols + width_3d)
    block_height = panel * (1.1 if rows == 1 else 0.95) * rows + 0.3  # one row: taller, for the 3-D view
    fig = _figure(width, block_height * len(variants))
    fig.get_layout_engine().set(w_pad=0.1)  # room for the 3-D views' z labels at the right edge
    # the foot (legend and colour bar) is sized once its legend is known
    stack = fig.add_gridspec(len(variants) + 1, 1, wspace=0, hspace=0)
    *blocks, foot = (fig.add_subfigure(stack[k]) for k in range(len(variants) + 1))
    every = np.concatenate([runs[v].returns for v in variants])
    max_it = max(max(int(r.iteration.max()), 1) for r in runs.values())
    norm = Normalize(vmin=1, vmax=max_it)
    mappable, axes = None, []
    for block, v in zip(blocks, variants):
        run = runs[v]
        nd = pareto_mask(run.returns)
        grid = block.add_gridspec(rows, cols + 1, width_ratios=[1] * cols + [width_3d])
        for n, (i, j) in enumerate(pairs):
            ax = block.add_subplot(grid[n // cols, n % cols], label=f"{v}: objectives {i}, {j}")
            mappable = _nd_members(ax, run, run.returns[:, [i, j]], nd, norm) or mappable
            ax.set_xlim(*_limits(every[:, i]))
            ax.set_ylim(*_limits(every[:, j]))
            ax.set_xlabel(names[i], fontsize="small")
            ax.set_ylabel(names[j], fontsize="small")
            ax.tick_params(labelsize="x-small")
            ax.grid(alpha=0.3)
            axes.append(ax)
        ax3 = block.add_subplot(grid[:, cols], projection="3d", label=f"{v}: 3-D")
        mappable = _nd_members(ax3, run, run.returns[:, :3], nd, norm) or mappable
        for k, axis in enumerate((ax3.set_xlim, ax3.set_ylim, ax3.set_zlim)):
            axis(*_limits(every[:, k]))
        ax3.set_xlabel(names[0], fontsize="small", labelpad=0)
        ax3.set_ylabel(names[1], fontsize="small", labelpad=0)
        ax3.set_zlabel(names[2], fontsize="small", labelpad=0)
        ax3.tick_params(labelsize="x-small", pad=0)
        ax3.set_box_aspect(None, zoom=0.9 if rows == 1 else 0.8)  # in a tall cell the cube fills its width
        for axis in (ax3.xaxis, ax3.yaxis, ax3.zaxis):
            axis.set_major_locator(MaxNLocator(4))
        ax3.set_title("3-D view" if m == 3 else "3-D view, objectives 0-2", fontsize="small")
        axes.append(ax3)
        block.suptitle(label(v), fontsize="medium", fontweight="bold")
    foot_height = _nd_foot(foot, axes, mappable)
    stack.set_height_ratios([block_height] * len(variants) + [foot_height])
    fig.set_size_inches(width, block_height * len(variants) + foot_height + 0.3)
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
    ax.plot(
        x[ok],
        mean[ok],
        color=colour,
        lw=1.6,
        ls=ls,
        drawstyle="steps-post",
        label=f"{name} (mean of {n} seed{'s' if n > 1 else ''})",
    )
    if n > 1:
        ax.fill_between(
            x[ok],
            (mean - sem)[ok],
            (mean + sem)[ok],
            step="post",
            color=colour,
            alpha=0.25 if ls == "-" else 0.12,
            lw=0,
        )


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
    for v in methods_in(runs):
        rs = [r for r in runs if r.method == v]
        c = colour(v)
        its = np.unique(np.concatenate([r.history["iteration"] for r in rs]))
        grid = np.unique(np.concatenate([r.history["env_samples"] for r in rs]))
        for key, ls, kind in HISTORY_CURVES:
            name = f"{label(v)}, {kind}"
            _band(
                ax_it,
                its,
                np.stack([step_values(r.history["iteration"], r.history[key], its) for r in rs]),
                c,
                name,
                len(rs),
                ls,
            )
            _band(
                ax_s,
                grid,
                np.stack([step_values(r.history["env_samples"], r.history[key], grid) for r in rs]),
                c,
                name,
                len(rs),
                ls,
            )
    ax_it.set_xlabel("iteration")
    ax_it.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax_s.set_xlabel("env frames after the specialists")
    ax_it.set_ylabel("hypervolume")
    for ax in (ax_it, ax_s):
        ax.grid(alpha=0.3)
    _shared_legend(fig, [ax_it])
    fig.suptitle(f"Hypervolume of the population as each method runs: {env_id}")
    return fig


def total_frames_figure(runs: list[Run], env_id: str, width: float) -> Figure | None:
    """Re-evaluated hypervolume of the population against *total* env frames, the specialists'
    training included (score's `env_samples_specialists`; MORL/D: 0), per method: the comparison a
    fixed-sample-budget claim rests on. Each curve starts where its specialists' training ends
    (their front, the population before any child) and grows with the method's own frames;
    mean ± SEM over seeds on the union of their frame counts. A method whose runs do not all
    record their specialists' frames (imported specialists trained elsewhere, or artifacts made
    before the count was recorded) is left out; None when no method can be drawn."""
    drawn = [v for v in methods_in(runs) if all("env_samples_specialists" in r.metrics for r in runs if r.method == v)]
    if not drawn:
        return None
    fig = _figure(width, width * 0.45)
    ax = fig.subplots()
    for v in drawn:
        rs = [r for r in runs if r.method == v]
        xs = [r.history["env_samples"] + r.metrics["env_samples_specialists"] for r in rs]
        # from the point every seed has reached on (seeds' specialists may differ in frames)
        start = max(float(x[0]) for x in xs)
        grid = np.unique(np.concatenate(xs))
        grid = grid[grid >= start]
        ys = np.stack([step_values(x, r.history["hypervolume"], grid) for x, r in zip(xs, rs)])
        _band(ax, grid, ys, colour(v), label(v), len(rs))
    ax.set_xlabel("total env frames (the specialists' training included)")
    ax.set_ylabel("re-evaluated hypervolume")
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small", loc="best")
    fig.suptitle(f"Hypervolume against every env frame spent: {env_id}")
    return fig


def _sem(a: np.ndarray) -> float:
    return float(a.std(ddof=1) / np.sqrt(len(a))) if len(a) > 1 else 0.0


def cost_figure(runs: list[Run], env_id: str, width: float) -> Figure:
    """Re-evaluated hypervolume of the population against the cumulative core-seconds of the
    stage that made it (pipeline.reporting.cost), per method, as its front grows: a curve
    (mean ± SEM over seeds, each seed's step curve on the union of their core-seconds, from the
    first x at which every seed has a record, so the mean is always over all seeds) where the
    stage recorded per-iteration costs (extraction, interpolation), one point (mean ± SEM of
    both) at its total and final hypervolume where it recorded only its process's seconds. A
    method with no recorded cost is not drawn. Core-seconds on a log axis: methods differ by
    orders of magnitude."""
    from pipeline.reporting.cost import cost_curve, method_core_seconds

    fig = _figure(width, width * 0.45)
    ax = fig.subplots()
    for v in methods_in(runs):
        rs = [r for r in runs if r.method == v]
        curves = [c for r in rs if (c := cost_curve(r)) is not None]
        if curves:
            # from the point where every seed has a record on: before it the mean would be over
            # fewer seeds and could step down when a seed with a lower curve joins
            start = max(float(np.min(x)) for x, _ in curves)
            grid = np.unique(np.concatenate([x for x, _ in curves]))
            grid = grid[(grid > 0) & (grid >= start)]
            _band(ax, grid, np.stack([step_values(x, y, grid) for x, y in curves]), colour(v), label(v), len(curves))
            continue
        points = [(c, r.metrics["front"]["hypervolume"]) for r in rs if (c := method_core_seconds(r)) is not None]
        if points:
            x, y = np.array(points, dtype=float).T
            ax.errorbar(
                x.mean(),
                y.mean(),
                xerr=_sem(x),
                yerr=_sem(y),
                fmt="o",
                color=colour(v),
                label=f"{label(v)}: final front (mean of {len(x)} seed{'s' if len(x) > 1 else ''})",
            )
    ax.set_xscale("log")
    ax.set_xlabel("core-seconds of the stage making the front (cumulative; specialists not included)")
    ax.set_ylabel("re-evaluated hypervolume")
    ax.grid(alpha=0.3, which="both")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize="small", loc="best")
    fig.suptitle(f"Hypervolume against compute as each front grows: {env_id}")
    return fig


def interpolation_path(run: Run) -> tuple[np.ndarray, np.ndarray] | None:
    """For a 2-objective interpolation run (every member not a starting policy of origin
    "interpolated", in grid order, as stage interpolate writes them): the mixing weights l from
    0 (objective 0's specialist) to 1 (objective 1's) and the re-evaluated returns (len(l), 2) along
    them, the specialists (per objective its starting policy best on that objective, the one mixed)
    at the ends. None for any other run."""
    spec = run.origin == "specialist"
    rest = run.origin[~spec]
    if run.returns.shape[1] != 2 or not len(rest) or not np.all(rest == "interpolated") or run.objective is None:
        return None
    ends = []
    for k in (0, 1):
        mine = np.flatnonzero(spec & (run.objective == k))
        if not len(mine):
            return None
        ends.append(mine[np.argmax(run.returns[mine, k])])
    inner = run.returns[~spec]
    lam = np.concatenate([[0.0], np.arange(1, len(inner) + 1) / (len(inner) + 1), [1.0]])
    return lam, np.vstack([run.returns[ends[0]], inner, run.returns[ends[1]]])


def barrier_figure(runs: list[Run], names: list[str], env_id: str, seed: int, width: float) -> Figure | None:
    """Where interpolation loses: each objective's re-evaluated return along the interpolation
    path of seed `seed`'s specialists, one line per interpolation method (plain, aligned, aligned
    + REPAIR, RegMean: stage interpolate's variants), with the straight line between the
    specialists' returns as the no-barrier reference. None without a 2-objective interpolation run."""
    paths = {r.method: p for r in runs if r.seed == seed and (p := interpolation_path(r)) is not None}
    if not paths:
        return None
    fig, _, axes = _panels(2, width, 0.7)
    for k, ax in enumerate(axes):
        for v in (m for m in methods_in(runs) if m in paths):
            lam, ret = paths[v]
            ax.plot(lam, ret[:, k], "-o", ms=2.5, color=colour(v), label=label(v))
        lam, ret = next(iter(paths.values()))
        ax.plot([0, 1], [ret[0, k], ret[-1, k]], ":", color="grey", label="straight line between the specialists")
        ax.set_xlabel(f"mixing weight l (towards the {names[1]} specialist)")
        ax.set_ylabel(f"re-evaluated return: {names[k]}")
        ax.grid(alpha=0.3)
    _shared_legend(fig, axes)
    fig.suptitle(f"Interpolation path between seed {seed}'s specialists: {env_id}")
    return fig
