"""The report's figures: the fronts of one seed (one panel per method, starting policies apart
from what each method made) and the hypervolume history (vs iteration and vs env frames), with
the panel, legend, front-line and mean +- SEM band helpers the grid report's figures share.
Matplotlib `Figure`s rendered with Agg (no pyplot, no global backend state)."""

from __future__ import annotations

import warnings

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from pipeline.params.methods import colour, label
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


def _starting_policies(ax, run: Run, pts: np.ndarray) -> None:
    """The starting policies as stars, one colour per specialist (by its objective); smaller
    stars where a specialist gave a whole policy set."""
    spec = run.origin == "specialist"
    objective = run.objective if run.objective is not None else np.full(len(spec), -1)
    for k, n in run.starting_counts().items():
        sel = spec & (objective == k)
        name = "specialist" if k < 0 else f"specialist {k}"
        ax.scatter(
            pts[sel, 0],
            pts[sel, 1],
            marker="*",
            s=220 if n == 1 else 110,
            color=SPECIALIST_COLOURS[k % len(SPECIALIST_COLOURS)] if k >= 0 else "tab:red",
            edgecolors="black",
            lw=0.8,
            zorder=5,
            label=name if n == 1 else f"{name}: {n} starting policies",
        )


def front_figure(runs: dict[str, Run], names: list[str], env_id: str, seed: int, width: float) -> Figure:
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
