"""The front figure of the report for 2 and for 3+ objectives.

Fake runs are built in memory (no env, no training). For m = 2 the figure must stay what it
always was: its panels, titles, labels and every plotted array are checked against the runs
they were drawn from. For m >= 3 the figure shows, per method, every pairwise projection and a
3-D view, rings exactly the points non-dominated in all m objectives and draws the starting
policies apart from the children.
"""

from __future__ import annotations

import numpy as np
from matplotlib.colors import to_rgba

from pipeline.params.methods import colour, label
from pipeline.reporting.figures import front_figure
from pipeline.reporting.runs import Run

NAMES2 = ["x velocity", "energy efficiency"]
METHODS = ("mapex_td3", "warmup_only_td3")


def fake_run(method: str, returns: np.ndarray, n_specialists: int, seed: int = 0, per_specialist: int = 1) -> Run:
    """A run whose first n_specialists * per_specialist members are starting policies (specialist
    k's come k-th) and the rest children made in iterations 1, 2, ... (cycling up to 4)."""
    returns = np.asarray(returns, float)
    n, starts = len(returns), n_specialists * per_specialist
    origin = np.array(["specialist"] * starts + ["child"] * (n - starts))
    objective = np.array([k for k in range(n_specialists) for _ in range(per_specialist)] + [-1] * (n - starts))
    iteration = np.array([0] * starts + [1 + i % 4 for i in range(n - starts)])
    # on_front as the score stage writes it (front.csv: pareto_mask of the re-evaluated means)
    ge = (returns[:, None, :] >= returns[None, :, :]).all(-1)
    gt = (returns[:, None, :] > returns[None, :, :]).any(-1)
    on_front = ~(ge & gt).any(axis=0)
    metrics = {"front": {"hypervolume": 1.0}, "iterations": 4, "reference_point": [0.0] * returns.shape[1]}
    history = {
        "iteration": np.arange(5.0),
        "env_samples": np.arange(5.0) * 100,
        "hypervolume_extract": np.linspace(1, 2, 5),
        "hypervolume": np.linspace(1, 1.8, 5),
    }
    return Run(method, seed, metrics, returns, origin, iteration, on_front, history, None, objective)


def two_objective_runs() -> dict[str, Run]:
    rng = np.random.default_rng(3)
    a = np.vstack([[[100.0, -900.0], [-20.0, -50.0]], rng.uniform([-20, -900], [100, -50], size=(9, 2))])
    b = np.vstack([[[100.0, -900.0], [-20.0, -50.0]], rng.uniform([-20, -900], [100, -50], size=(6, 2))])
    return {"mapex_td3": fake_run("mapex_td3", a, 2), "warmup_only_td3": fake_run("warmup_only_td3", b, 2)}


def step_line(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = points[np.argsort(points[:, 0])]
    return p[:, 0], p[:, 1]


def test_two_objective_front_figure_is_unchanged():
    """The m = 2 figure as the report has always drawn it: one panel per method, the other
    methods' fronts dashed, the own front solid black, children coloured by iteration, the
    non-dominated children ringed, one star per specialist, shared legend, colorbar, title."""
    runs = two_objective_runs()
    fig = front_figure(runs, NAMES2, "mo-halfcheetah-v5", 7, 11.0)
    panels = [ax for ax in fig.axes if ax.get_label() != "<colorbar>"]
    assert len(panels) == 2 and len(fig.axes) == 3
    assert all(ax.name == "rectilinear" for ax in fig.axes)
    assert fig.get_suptitle() == "Re-evaluated fronts: mo-halfcheetah-v5, seed 7"
    assert fig.axes[2].get_ylabel() == "iteration (MOPDERL: generation)"
    for ax, v in zip(panels, METHODS):
        run, other = runs[v], runs[next(o for o in METHODS if o != v)]
        pts, child = run.returns, run.origin != "specialist"
        assert ax.get_title() == label(v)
        assert ax.get_xlabel() == NAMES2[0]
        assert ax.get_ylabel() == (NAMES2[1] if v == METHODS[0] else "")
        dashed, solid = ax.get_lines()
        for line, p, c, ls in (
            (dashed, other.returns[other.on_front], colour(other.method), "--"),
            (solid, pts[run.on_front], "black", "-"),
        ):
            x, y = step_line(p)
            np.testing.assert_array_equal(line.get_xdata(), x)
            np.testing.assert_array_equal(line.get_ydata(), y)
            assert line.get_drawstyle() == "steps-pre" and line.get_linestyle() == ls
            assert to_rgba(line.get_color()) == to_rgba(c)
        made, ring, *stars = ax.collections
        np.testing.assert_array_equal(made.get_offsets(), pts[child])
        np.testing.assert_array_equal(made.get_array(), run.iteration[child])
        np.testing.assert_array_equal(ring.get_offsets(), pts[child & run.on_front])
        assert len(ring.get_facecolors()) == 0 and ring.get_sizes()[0] == 70
        assert len(stars) == 2
        for k, star in enumerate(stars):
            np.testing.assert_array_equal(star.get_offsets(), pts[[k]])
            assert star.get_label() == f"specialist {k}" and star.get_sizes()[0] == 220
        assert [c.get_label() for c in ax.collections[:2]] == [
            "made by the method (colour: iteration)",
            "non-dominated",
        ]
    (legend,) = fig.legends
    assert [t.get_text() for t in legend.get_texts()] == [
        f"{label(METHODS[1])} front",
        f"{label(METHODS[0])} front",
        "made by the method (colour: iteration)",
        "non-dominated",
        "specialist 0",
        "specialist 1",
    ]
