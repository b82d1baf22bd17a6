"""The front figure of the report for 2 and for 3+ objectives.

Fake runs are built in memory (no env, no training). For m = 2 the figure must stay what it
always was: its panels, titles, labels and every plotted array are checked against the runs
they were drawn from. For m >= 3 the figure shows, per method, every pairwise projection and a
3-D view, rings exactly the points non-dominated in all m objectives and draws the starting
policies apart from the children.
"""

from __future__ import annotations

import csv
import itertools
import json
from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest
import torch
import typer
import yaml
from matplotlib.colors import to_rgba
from typer.testing import CliRunner

from pipeline.core.nets import Actor
from pipeline.core.population import Member, actor_state, save_population
from pipeline.evaluation.metrics import mean_sem
from pipeline.reporting.figures import front_caption, front_figure, history_figure
from pipeline.reporting.presentation import colour, label
from pipeline.reporting.runs import Run
from pipeline.reporting.tables import fmt_num
from stages.evaluate import evaluate
from stages.report import report
from stages.score import score

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


def test_two_objective_caption_is_unchanged():
    runs = list(two_objective_runs().values())
    assert front_caption(runs, 3) == (
        "Seed 3: re-evaluated returns of every member, starting policies as stars (one colour per "
        "specialist), what each method made coloured by iteration; MAPEX-TD3 vs warm-up only (TD3) side by side."
    )


# ---------------------------------------------------------------- m >= 3


NAMES4 = ["x velocity", "jump height", "energy", "y velocity"]


def dominates(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(all(x >= y for x, y in zip(a, b)) and any(x > y for x, y in zip(a, b)))


def non_dominated_rows(points: np.ndarray) -> np.ndarray:
    """Written out plainly: row i is kept unless some other row dominates it."""
    return np.array([not any(dominates(q, p) for q in points) for p in points])


def tricky_returns(m: int) -> np.ndarray:
    """Starting policies first (one per objective), then children. Some points are non-dominated
    in all m objectives while dominated in a projection (p vs q on objectives 0, 1), some are
    dominated outright, one non-dominated point is duplicated and one specialist is dominated;
    the random children (sum 2.5) can dominate neither p (sum m) nor q (sum 4)."""
    rng = np.random.default_rng(m)
    specialists = np.full((m, m), 0.0)
    specialists[np.arange(m), np.arange(m)] = 10.0
    specialists[m - 1] = 0.5  # dominated by p below
    p = np.ones(m)
    q = np.array([2.0, 2.0] + [0.0] * (m - 2))
    children = np.vstack(
        [p, q, q, 0.5 * np.ones(m), [1.5, 1.5] + [0.5] * (m - 2), 2.5 * rng.dirichlet(np.ones(m), size=12)]
    )
    return np.vstack([specialists, children])


def nd_runs(m: int) -> dict[str, Run]:
    rng = np.random.default_rng(10 + m)
    a = tricky_returns(m)
    b = np.vstack([a[:m], rng.uniform(0, 4, size=(9, m))])
    return {"mapex_td3": fake_run("mapex_td3", a, m), "warmup_only_td3": fake_run("warmup_only_td3", b, m)}


def panels(fig, method: str) -> dict[str, object]:
    """The front figure's axes of `method`, by their label ("objectives i, j" or "3-D")."""
    prefix = f"{method}: "
    return {ax.get_label().removeprefix(prefix): ax for ax in fig.axes if ax.get_label().startswith(prefix)}


def collection(ax, name: str):
    (found,) = [c for c in ax.collections if c.get_label() == name]
    return found


def coords(coll, ndim: int) -> np.ndarray:
    """The data coordinates a scatter was given: (n, 2) offsets, or (n, 3) on a 3-D axes."""
    if ndim == 3:  # matplotlib keeps a 3-D scatter's data coordinates only in this private attribute
        return np.column_stack([np.asarray(c, float) for c in coll._offsets3d])
    return np.asarray(coll.get_offsets(), float)


def same_rows(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal as multisets of rows (order ignored, duplicates counted)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    return a.shape == b.shape and np.array_equal(a[np.lexsort(a.T)], b[np.lexsort(b.T)])


@pytest.mark.parametrize(("m", "n_pairs"), [(3, 3), (4, 6)])
def test_one_panel_per_pair_of_objectives_and_a_3d_view(m, n_pairs):
    runs = nd_runs(m)
    names = NAMES4[:m]
    fig = front_figure(runs, names, "mo-hopper-v5", 0, 11.0)
    for v in METHODS:
        got = panels(fig, v)
        pairs = [k for k in got if k.startswith("objectives")]
        assert len(pairs) == n_pairs == m * (m - 1) // 2
        assert sorted(pairs) == [f"objectives {i}, {j}" for i in range(m) for j in range(i + 1, m)]
        for i in range(m):
            for j in range(i + 1, m):
                ax = got[f"objectives {i}, {j}"]
                assert ax.name == "rectilinear"
                assert (ax.get_xlabel(), ax.get_ylabel()) == (names[i], names[j])
        ax3 = got["3-D"]
        assert ax3.name == "3d"
        assert (ax3.get_xlabel(), ax3.get_ylabel(), ax3.get_zlabel()) == tuple(names[:3])
        assert ("objectives 0-2" in ax3.get_title()) == (m > 3)
        assert len(got) == n_pairs + 1
    # the methods' blocks and the suptitle
    assert sorted(sf.get_suptitle() for sf in fig.subfigs if sf.get_suptitle()) == sorted(label(v) for v in METHODS)
    assert fig.get_suptitle() == "Re-evaluated fronts: mo-hopper-v5, seed 0"
    # the same limits for one pair in every method's block, so the blocks compare by eye
    a, b = (panels(fig, v) for v in METHODS)
    for key in a:
        assert a[key].get_xlim() == b[key].get_xlim() and a[key].get_ylim() == b[key].get_ylim()


@pytest.mark.parametrize("m", [3, 4])
def test_ringed_points_are_the_non_dominated_ones_in_all_objectives(m):
    runs = nd_runs(m)
    fig = front_figure(runs, NAMES4[:m], "mo-hopper-v5", 0, 11.0)
    for v, run in runs.items():
        nd = non_dominated_rows(run.returns)
        assert 0 < nd.sum() < len(nd)
        for key, ax in panels(fig, v).items():
            cols = [0, 1, 2] if key == "3-D" else [int(c) for c in key.removeprefix("objectives ").split(", ")]
            ring = collection(ax, f"non-dominated (all {m} objectives)")
            assert len(ring.get_facecolors()) == 0  # rings, not dots
            assert same_rows(coords(ring, len(cols)), run.returns[nd][:, cols]), (v, key)
    # the tricky points: p and q are both ringed although q dominates p on objectives 0 and 1;
    # the point dominated by p and the dominated specialist are not
    run = runs["mapex_td3"]
    nd = non_dominated_rows(run.returns)
    p, q = m, m + 1
    assert nd[p] and nd[q] and nd[q + 1] and not nd[q + 2] and not nd[m - 1]
    assert dominates(run.returns[q, :2], run.returns[p, :2])
    # so in the (0, 1) panel the rings are not the 2-D front of what it shows
    ring = coords(collection(panels(fig, "mapex_td3")["objectives 0, 1"], f"non-dominated (all {m} objectives)"), 2)
    assert not same_rows(ring, run.returns[non_dominated_rows(run.returns[:, :2])][:, :2])


def test_starting_policies_are_drawn_apart_from_the_children():
    m = 3
    runs = nd_runs(m)
    # MAPEX-TD3 starts from 2 policies per specialist (as from policy sets), warm-up only from 1
    r = tricky_returns(m)
    sets = np.vstack([r[:m], r[:m] + 0.25])[[0, 3, 1, 4, 2, 5]]  # specialist k's two policies in a row
    runs["mapex_td3"] = fake_run("mapex_td3", np.vstack([sets, r[m:]]), m, per_specialist=2)
    fig = front_figure(runs, NAMES4[:m], "mo-hopper-v5", 0, 11.0)
    for v, run in runs.items():
        spec = run.origin == "specialist"
        per = run.starting_counts()
        for key, ax in panels(fig, v).items():
            cols = [0, 1, 2] if key == "3-D" else [int(c) for c in key.removeprefix("objectives ").split(", ")]
            made = collection(ax, "made by the method (colour: iteration)")
            assert same_rows(coords(made, len(cols)), run.returns[~spec][:, cols])
            np.testing.assert_array_equal(made.get_array(), run.iteration[~spec])
            for k in range(m):
                name = f"specialist {k}" if per[k] == 1 else f"specialist {k}: {per[k]} starting policies"
                star = collection(ax, name)
                assert same_rows(coords(star, len(cols)), run.returns[spec & (run.objective == k)][:, cols])
            drawn = sum(len(coords(c, len(cols))) for c in ax.collections if c.get_label().startswith("specialist"))
            assert drawn == spec.sum()
    assert runs["mapex_td3"].starting_counts() == {0: 2, 1: 2, 2: 2}
    # one legend for the figure naming every kind of mark once, and the iteration colour bar
    texts = [t.get_text() for sf in fig.subfigs for lg in sf.legends for t in lg.get_texts()]
    assert "non-dominated (all 3 objectives)" in texts and "made by the method (colour: iteration)" in texts
    assert "specialist 0: 2 starting policies" in texts and "specialist 0" in texts and len(texts) == len(set(texts))
    (bar,) = fig.subfigs[-1].axes
    assert bar.get_xlabel() == "iteration (MOPDERL: generation)"
    assert bar.get_xlim() == (1, max(r.iteration.max() for r in runs.values()))


def test_three_objective_front_figure_png(tmp_path):
    """The figure renders at the report's default width to a PNG of a sensible size."""
    fig = front_figure(nd_runs(3), NAMES4[:3], "mo-hopper-v5", 0, 11.0)
    fig.savefig(tmp_path / "front.png", dpi=100)
    img = mpimg.imread(tmp_path / "front.png")
    assert img.shape[1] == 1100 and 500 < img.shape[0] < 1100 and img[..., :3].std() > 0.01


def test_captions_for_three_and_four_objectives():
    three = front_caption(list(nd_runs(3).values()), 1)
    assert "each pair of the 3 objectives, then a 3-D view." in three and "MAPEX-TD3 vs warm-up only (TD3)" in three
    assert "non-dominated in all 3 objectives" in three
    assert "a 3-D view (the first three objectives)" in front_caption(list(nd_runs(4).values()), 1)


def test_history_figure_with_three_objectives():
    runs = list(nd_runs(3).values())
    fig = history_figure(runs, "mo-hopper-v5", 11.0)
    ax_it, ax_s = fig.axes
    assert len(ax_it.get_lines()) == len(ax_s.get_lines()) == 2 * len(runs)  # extraction-time and re-evaluated
    np.testing.assert_array_equal(ax_it.get_lines()[0].get_ydata(), runs[0].history["hypervolume_extract"])


# ---------------------------------------------------------------- the whole report, 3 objectives

HOPPER = "mo-hopper-v5"  # x velocity, jump height, energy
HOPPER_NAMES = ["x velocity", "jump height", "energy"]


def _app() -> typer.Typer:
    app = typer.Typer()

    @app.callback()
    def main() -> None:
        torch.set_num_threads(1)

    for name, fn in (("evaluate", evaluate), ("score", score), ("report", report)):
        app.command(name)(fn)
    return app


def invoke(app: typer.Typer, *args) -> str:
    result = CliRunner().invoke(app, [str(a) for a in args])
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        raise result.exception
    assert result.exit_code == 0, result.output
    return result.output


def hopper_population(path: Path, seed: int, method: str) -> None:
    """3 specialists (one per objective, the same for both methods of a seed) and 4 children of
    random small actors; the returns recorded here stand for the extraction-time ones."""
    low, high = [-1.0] * 3, [1.0] * 3
    members = []
    for i in range(7):
        specialist = i < 3
        torch.manual_seed(1000 * seed + i + (0 if specialist or method == "mapex_td3" else 100))
        members.append(
            Member(
                origin="specialist" if specialist else "child",
                objective=i if specialist else None,
                iteration=0 if specialist else i - 2,
                parents=[] if specialist else [0, 1, 2],
                target_weight=None if specialist else [0.4, 0.3, 0.3],
                returns=[float(i), float(-i), float(-2 * i)],
                returns_std=[1.0, 1.0, 1.0],
                eval_episodes=2,
                env_samples=100 * (i + 1),
                hidden_sizes=[16, 16],
                actor=actor_state(Actor(11, 3, [16, 16], low, high)),
                policy_name="policy" if specialist else None,
            )
        )
    meta = dict(env_id=HOPPER, obs_dim=11, act_dim=3, n_objectives=3, action_low=low, action_high=high)
    save_population(path, members, {**meta, "seed": seed, "params": {}, "method": method})


@pytest.fixture(scope="module")
def hopper_report(tmp_path_factory) -> Path:
    """evaluate, score and report on 3-objective populations: 2 seeds x MAPEX-TD3, warm-up only."""
    root = tmp_path_factory.mktemp("hopper")
    params = root / "params.yaml"
    env = {"id": HOPPER, "max_episode_steps": 30, "reference_point": [-100.0, -100.0, -100.0]}
    env["objective_names"] = HOPPER_NAMES
    params.write_text(
        yaml.safe_dump(
            {"env": env, "evaluate": {"episodes": 2}, "report": {"dpi": 60}, "seeds": [0, 1], "objectives": [0, 1, 2]}
        )
    )
    app = _app()
    for method in METHODS:
        for seed in (0, 1):
            pop, ev, sc = (root / stage / method / f"seed{seed}" for stage in ("extract", "evaluate", "score"))
            hopper_population(pop / "population.pt", seed, method)
            invoke(
                app, "evaluate", "--population", pop / "population.pt", "--out", ev, "--seed", seed, "--params", params
            )
            invoke(
                app, "score", "--population", pop / "population.pt", "--evaluated", ev, "--out", sc, "--params", params
            )
    args = ["--evaluated", root / "evaluate", "--scored", root / "score", "--out", root / "report", "--params", params]
    invoke(app, "report", *args)
    return root


def test_three_objective_report(hopper_report):
    out = hopper_report / "report"
    assert sorted(p.name for p in out.iterdir()) == [
        "front_seed0.png",
        "front_seed1.png",
        "hypervolume.png",
        "report.md",
    ]
    for name in ("front_seed0.png", "front_seed1.png", "hypervolume.png"):
        img = mpimg.imread(out / name)
        assert img.shape[0] > 200 and img.shape[1] > 300 and img[..., :3].std() > 0.01
    text = (out / "report.md").read_text()
    assert "- objectives: 0: x velocity, 1: jump height, 2: energy" in text
    assert "- hypervolume reference point: [-100.0, -100.0, -100.0]" in text
    # the specialists' own-objective table has a column per objective and a row per seed
    own = text.split("## Specialists on their own objectives", 1)[1].split("## Metrics", 1)[0]
    rows = [line for line in own.splitlines() if line.startswith("|")]
    assert (
        rows[0]
        == "| specialists | seed | x velocity (objective 0) | jump height (objective 1) | energy (objective 2) |"
    )
    assert [r.split("|")[1:3] for r in rows[2:]] == [[" TD3 ", " 0 "], [" TD3 ", " 1 "]]
    assert all(len(r.split("|")) == 7 for r in rows)
    # its cells are each specialist's re-evaluated return on its own objective
    evaluated = read_csv(hopper_report / "evaluate" / "mapex_td3" / "seed1" / "evaluated.csv")
    own_values = [float(next(r for r in evaluated if r["objective"] == str(k))[f"obj{k}"]) for k in range(3)]
    assert [c.strip() for c in rows[3].split("|")[3:6]] == [fmt_num(v) for v in own_values]
    # Table 1 and the details table, from the 3-objective metrics
    hv = [
        json.loads((hopper_report / "score" / "mapex_td3" / f"seed{s}" / "metrics.json").read_text())["front"]
        for s in (0, 1)
    ]
    table = next(line for line in text.splitlines() if line.startswith(f"| {HOPPER} |"))
    mean, sem = mean_sem([m["hypervolume"] for m in hv])
    assert table.split("|")[2].strip() == f"{fmt_num(mean)} ± {fmt_num(sem)}"
    assert "With 3 objectives the front is a surface, not a curve" in text
    caption = "each pair of the 3 objectives, then a 3-D view"
    assert text.count(caption) == 4  # two front figures: alt text and caption each


def test_three_objective_metrics_match_the_evaluated_returns(hopper_report):
    """score's front and hypervolume for 3 objectives, from evaluated.csv and an independent check."""
    run = hopper_report / "score" / "warmup_only_td3" / "seed0"
    rows = read_csv(hopper_report / "evaluate" / "warmup_only_td3" / "seed0" / "evaluated.csv")
    pts = np.array([[float(r[f"obj{k}"]) for k in range(3)] for r in rows])
    nd = non_dominated_rows(pts)
    assert sorted(int(r["id"]) for r in read_csv(run / "front.csv")) == list(np.flatnonzero(nd))
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["front"]["cardinality"] == len(np.unique(pts[nd], axis=0))
    assert metrics["front"]["hypervolume"] == pytest.approx(box_union_volume(pts[nd], np.full(3, -100.0)), rel=1e-9)


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def box_union_volume(points: np.ndarray, ref: np.ndarray) -> float:
    """Volume of the union of the boxes [ref, p] by a grid over the distinct coordinates: each
    cell of the grid is inside the union when some point is >= its upper corner."""
    p = points[(points > ref).all(axis=1)]
    if len(p) == 0:
        return 0.0
    edges = [np.unique(np.concatenate([[r], p[:, k]])) for k, r in enumerate(ref)]
    total = 0.0
    for cell in itertools.product(*(range(len(e) - 1) for e in edges)):
        upper = np.array([e[i + 1] for e, i in zip(edges, cell)])
        if (p >= upper).all(axis=1).any():
            total += float(np.prod([e[i + 1] - e[i] for e, i in zip(edges, cell)]))
    return total


def test_grid_fronts_figure_projects_a_three_objective_cell_and_keeps_two_objective_cells():
    """The sweep's grid report: a 3-objective cell shows its front points (non-dominated in all 3)
    projected onto objectives 0 and 1, titled as a projection; a 2-objective cell keeps its
    staircase line and generic labels."""
    from pipeline.reporting.grid import Cell, grid_fronts_figure

    rng = np.random.default_rng(5)
    three = fake_run("mapex_td3", rng.uniform(0, 10, size=(12, 3)), 3)
    two = two_objective_runs()["mapex_td3"]
    cells = [
        Cell("mo-hopper-v5", "mo-hopper-v5", [three], names=["x velocity", "jump height", "energy efficiency"]),
        Cell("mo-halfcheetah-v5", "mo-halfcheetah-v5", [two]),
    ]
    fig = grid_fronts_figure(cells, 8.0)
    ax3, ax2 = fig.axes[:2]
    assert ax3.get_title() == "mo-hopper-v5 (projection of 3 objectives)"
    assert (ax3.get_xlabel(), ax3.get_ylabel()) == ("x velocity", "jump height")
    assert not ax3.get_lines()
    offsets = np.asarray(ax3.collections[0].get_offsets())
    np.testing.assert_allclose(offsets, three.returns[three.on_front][:, :2])
    assert ax2.get_title() == "mo-halfcheetah-v5" and (ax2.get_xlabel(), ax2.get_ylabel()) == (
        "objective 0",
        "objective 1",
    )
    (line,) = ax2.get_lines()
    x, y = step_line(two.returns[two.on_front])
    np.testing.assert_allclose(line.get_xdata(), x)
    np.testing.assert_allclose(line.get_ydata(), y)
