"""Stages evaluate and report end to end through the real `mapex` typer app, on tiny synthetic
populations (random [16, 16] actors on HalfCheetah, 50-step episodes, 2 episodes a member)."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from typer.testing import CliRunner

from pipeline.envs import make_env
from pipeline.evaluation import eval_seeds, evaluate_policy
from pipeline.metrics import hypervolume
from pipeline.nets import Actor
from pipeline.pareto import pareto_mask
from pipeline.population import Member, actor_state, load_population, member_actor, save_population
from pipeline.report import Run, hv_verdict
from stages.cli import app

ENV_ID = "mo-halfcheetah-v5"
REF = [-100.0, -4500.0]
CAP = 50
EPISODES = 2
SEEDS = (0, 1)
VARIANTS = ("mapex", "warmup_only")


def write_params(directory: Path, env: dict | None = None, evaluate: dict | None = None) -> Path:
    data = {
        "env": {"id": ENV_ID, "max_episode_steps": CAP, "reference_point": REF, **(env or {})},
        "evaluate": {"episodes": EPISODES, **(evaluate or {})},
        "report": {"dpi": 60},
        "seeds": list(SEEDS),
    }
    data["env"] = {k: v for k, v in data["env"].items() if v is not None}
    path = directory / "params.yaml"
    directory.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(data))
    return path


def make_population(path: Path, seed: int, variant: str, env_id: str = ENV_ID) -> None:
    """2 specialists (the same for every variant of a seed, as in a real run) + 3 children."""
    low, high = [-1.0] * 6, [1.0] * 6
    members = []
    for i in range(5):
        specialist = i < 2
        torch.manual_seed(1000 * seed + i + (0 if specialist or variant == "mapex" else 100))
        actor = Actor(17, 6, [16, 16], low, high)
        members.append(Member(
            origin="specialist" if specialist else "child", objective=i if specialist else None,
            iteration=0 if specialist else i - 1, parents=[] if specialist else [0, 1],
            target_weight=None if specialist else [0.6, 0.8],
            returns=[float(10 * i - 20), float(-100 * i)], returns_std=[1.0, 2.0], eval_episodes=5,
            env_samples=250 * (i + 1), hidden_sizes=[16, 16], actor=actor_state(actor)))
    meta = dict(env_id=env_id, obs_dim=17, act_dim=6, n_objectives=2, action_low=low, action_high=high,
                seed=seed, objective_names=None, reference_point=REF, params={}, variant=variant)
    save_population(path, members, meta)


def invoke(*args) -> tuple[int, str]:
    result = CliRunner().invoke(app, [str(a) for a in args])
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        raise result.exception
    return result.exit_code, result.output


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def write_history(path: Path, hvs: list[float]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = ["iteration,population,front_size,hypervolume,env_samples"]
    lines += [f"{i},{2 + i},2,{hv},{500 + 250 * i}" for i, hv in enumerate(hvs)]
    path.write_text("\n".join(lines) + "\n")


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    """Populations, evaluate outputs and extraction histories for 2 seeds x 2 variants."""
    root = tmp_path_factory.mktemp("runs")
    params = write_params(root)
    for v in VARIANTS:
        for s in SEEDS:
            make_population(root / "extract" / v / f"seed{s}" / "population.pt", s, v)
            write_history(root / "extract" / v / f"seed{s}" / "history.csv", [1e5, 1.5e5, 1.6e5, 1.7e5])
            code, out = invoke("evaluate", "--population", root / "extract" / v / f"seed{s}" / "population.pt",
                               "--out", root / "evaluate" / v / f"seed{s}", "--seed", s, "--params", params)
            assert code == 0, out
    return root


# ---------------------------------------------------------------- evaluate


def test_evaluated_csv_rows_columns_and_front_flags(runs):
    run = runs / "evaluate" / "mapex" / "seed0"
    rows = read_csv(run / "evaluated.csv")
    assert [r["id"] for r in rows] == ["0", "1", "2", "3", "4"]
    assert [r["origin"] for r in rows] == ["specialist"] * 2 + ["child"] * 3
    assert set(rows[0]) >= {"iteration", "parents", "obj0", "obj1", "obj0_std", "obj1_std",
                            "obj0_extract", "obj1_extract", "on_front"}
    members, _ = load_population(runs / "extract" / "mapex" / "seed0" / "population.pt")
    for r, m in zip(rows, members):  # extraction-time returns carried over unchanged
        assert [float(r["obj0_extract"]), float(r["obj1_extract"])] == m.returns
        assert float(r["obj0_std"]) >= 0 and float(r["obj1_std"]) >= 0
    means = np.array([[float(r["obj0"]), float(r["obj1"])] for r in rows])
    flags = np.array([r["on_front"] == "1" for r in rows])
    np.testing.assert_array_equal(flags, pareto_mask(means))
    front = read_csv(run / "front.csv")
    assert sorted(int(r["id"]) for r in front) == list(np.flatnonzero(flags))
    assert [float(r["obj0"]) for r in front] == sorted(float(r["obj0"]) for r in front)


def test_metrics_json_consistent_with_csv(runs):
    run = runs / "evaluate" / "mapex" / "seed0"
    metrics = json.loads((run / "metrics.json").read_text())
    rows = read_csv(run / "evaluated.csv")
    means = np.array([[float(r["obj0"]), float(r["obj1"])] for r in rows])
    on_front = means[[r["on_front"] == "1" for r in rows]]
    assert metrics["front"]["hypervolume"] == pytest.approx(hypervolume(on_front, REF))
    assert metrics["specialists"]["hypervolume"] == pytest.approx(hypervolume(means[:2], REF))
    assert metrics["specialists"]["hypervolume"] <= metrics["front"]["hypervolume"] + 1e-9
    assert metrics["hv_ratio_vs_specialists"] == pytest.approx(
        metrics["front"]["hypervolume"] / metrics["specialists"]["hypervolume"])
    assert metrics["front"]["cardinality"] == len(np.unique(on_front, axis=0))
    assert 1 <= metrics["front"]["distinct_count"] <= metrics["front"]["cardinality"]
    assert 0 < metrics["front"]["hv_fraction"] <= 1
    assert metrics["ideal_point"] == pytest.approx(means.max(axis=0).tolist())
    assert (metrics["env_id"], metrics["variant"], metrics["seed"], metrics["population"]) == (ENV_ID, "mapex", 0, 5)
    assert metrics["episodes"] == EPISODES and metrics["env_samples_evaluation"] == 5 * EPISODES * CAP
    extract = np.array([[float(r["obj0_extract"]), float(r["obj1_extract"])] for r in rows])
    assert metrics["extraction_hypervolume"] == pytest.approx(hypervolume(extract, REF))


def test_reevaluation_uses_the_fresh_seed_stream(runs):
    """Member 2 re-evaluated by hand on stream 1 reproduces the CSV; stream 0 (extraction's) does not."""
    members, meta = load_population(runs / "extract" / "mapex" / "seed1" / "population.pt")
    envs = [make_env(ENV_ID, CAP) for _ in range(EPISODES)]
    fresh = evaluate_policy(member_actor(members[2], meta), envs, eval_seeds(1, 1, 2, EPISODES)).mean
    old = evaluate_policy(member_actor(members[2], meta), envs, eval_seeds(1, 0, 2, EPISODES)).mean
    row = read_csv(runs / "evaluate" / "mapex" / "seed1" / "evaluated.csv")[2]
    np.testing.assert_allclose([float(row["obj0"]), float(row["obj1"])], fresh, rtol=1e-6)
    assert not np.allclose(fresh, old)


def test_specialists_score_the_same_in_both_variants(runs):
    a = json.loads((runs / "evaluate" / "mapex" / "seed0" / "metrics.json").read_text())
    b = json.loads((runs / "evaluate" / "warmup_only" / "seed0" / "metrics.json").read_text())
    # hv_fraction and distinct_count are relative to each run's own [reference, ideal] box
    for key in ("hypervolume", "sparsity", "expected_utility", "cardinality"):
        assert a["specialists"][key] == b["specialists"][key]
    assert a["front"] != b["front"]  # the children differ


def test_evaluate_is_deterministic(runs, tmp_path):
    code, out = invoke("evaluate", "--population", runs / "extract" / "mapex" / "seed0" / "population.pt",
                       "--out", tmp_path / "again", "--seed", 0, "--params", write_params(tmp_path))
    assert code == 0, out
    for name in ("evaluated.csv", "front.csv", "metrics.json"):
        assert (tmp_path / "again" / name).read_text() == (runs / "evaluate" / "mapex" / "seed0" / name).read_text()


def _evaluate_fails(tmp_path: Path, population: Path, params: Path, seed: int = 0) -> str:
    out_dir = tmp_path / "out"
    code, out = invoke("evaluate", "--population", population, "--out", out_dir, "--seed", seed, "--params", params)
    assert code == 2, out
    assert not out_dir.exists(), "nothing may be written on bad input"
    return out


def test_evaluate_missing_population(tmp_path):
    out = _evaluate_fails(tmp_path, tmp_path / "nope.pt", write_params(tmp_path))
    assert "nope.pt" in out and "not found" in out


def test_evaluate_truncated_population(tmp_path):
    good = tmp_path / "good.pt"
    make_population(good, 0, "mapex")
    bad = tmp_path / "truncated.pt"
    bad.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    out = _evaluate_fails(tmp_path, bad, write_params(tmp_path))
    assert "truncated.pt" in out


def test_evaluate_env_mismatch(tmp_path):
    pop = tmp_path / "swimmer.pt"
    make_population(pop, 0, "mapex", env_id="mo-swimmer-v5")
    out = _evaluate_fails(tmp_path, pop, write_params(tmp_path))
    assert "swimmer.pt" in out and "mo-swimmer-v5" in out and ENV_ID in out


def test_evaluate_seed_mismatch(tmp_path):
    pop = tmp_path / "pop.pt"
    make_population(pop, 0, "mapex")
    out = _evaluate_fails(tmp_path, pop, write_params(tmp_path), seed=3)
    assert "pop.pt" in out and "seed" in out


@pytest.mark.parametrize("ref, needle", [(None, "missing"), ([-100.0], "1 values")])
def test_evaluate_bad_reference_point(tmp_path, ref, needle):
    pop = tmp_path / "pop.pt"
    make_population(pop, 0, "mapex")
    out = _evaluate_fails(tmp_path, pop, write_params(tmp_path, env={"reference_point": ref}))
    assert "env.reference_point" in out and needle in out


def test_evaluate_rejects_extraction_stream(tmp_path):
    pop = tmp_path / "pop.pt"
    make_population(pop, 0, "mapex")
    out = _evaluate_fails(tmp_path, pop, write_params(tmp_path, evaluate={"seed_stream": 0}))
    assert "evaluate.seed_stream" in out


# ---------------------------------------------------------------- report


@pytest.fixture(scope="module")
def report_dir(runs) -> Path:
    code, out = invoke("report", "--evaluated", runs / "evaluate", "--extracted", runs / "extract",
                       "--out", runs / "report", "--params", runs / "params.yaml")
    assert code == 0, out
    return runs / "report"


def test_report_files(report_dir):
    names = sorted(p.name for p in report_dir.iterdir())
    assert names == ["front_seed0.png", "front_seed1.png", "hypervolume.png", "report.md"]
    import matplotlib.image as mpimg

    for name in names[:-1]:
        data = (report_dir / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000
        img = mpimg.imread(report_dir / name)
        assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 300
        assert img[..., :3].std() > 0.01  # not a blank canvas
    text = (report_dir / "report.md").read_text()
    for name in names[:-1]:
        assert f"]({name})" in text
    assert not (report_dir.parent / "report.partial").exists()


def test_report_table_rows(report_dir):
    text = (report_dir / "report.md").read_text()
    tables = [line for line in text.splitlines() if line.startswith("|")]
    header = tables[0].split("|")[1:-1]
    assert header[0].strip() == "Environment" and len(header) == 1 + 4 * 3
    assert any("Hypervolume" in h and "specialists only" in h for h in header)
    env_rows = [t for t in tables if t.startswith(f"| {ENV_ID} |")]
    assert len(env_rows) == 1
    assert all("±" in c for c in env_rows[0].split("|")[2:5])  # two seeds: mean ± SEM
    for variant in ("| MAPEX |", "| warm-up only |", "| specialists only |"):
        assert sum(t.startswith(variant) for t in tables) == 1


def test_report_verdict_matches_numbers(runs, report_dir):
    hv = {v: [json.loads((runs / "evaluate" / v / f"seed{s}" / "metrics.json").read_text())["front"]["hypervolume"]
              for s in SEEDS] for v in VARIANTS}
    d = np.array(hv["mapex"]) - np.array(hv["warmup_only"])
    margin = 2 * d.std(ddof=1) / np.sqrt(len(d))
    verb = "beat" if d.mean() > margin else "lost to" if d.mean() < -margin else "tied with"
    text = (report_dir / "report.md").read_text()
    assert f"(MAPEX) {verb} warm-up only" in text
    assert f"higher in {int((d > 0).sum())} of 2" in text


def _run(variant: str, seed: int, hv: float) -> Run:
    metrics = {"front": {"hypervolume": hv}, "iterations": 4}
    empty = np.zeros(0)
    return Run(variant, seed, metrics, np.zeros((0, 2)), empty, empty, empty, {})


@pytest.mark.parametrize(
    "mapex_hv, warm_hv, outcome",
    [
        # 3 seeds, paired differences 1.0, 1.1, 0.9: mean 1.0, SEM 0.058 -> beyond 2 SEM: beat
        ([3.0, 5.1, 7.9], [2.0, 4.0, 7.0], "beat"),
        ([2.0, 4.0, 7.0], [3.0, 5.1, 7.9], "lost"),
        # differences +1, -1.2, +0.5: mean 0.1, SEM 0.65 -> inside the noise: tied, though 2 of 3 are higher
        ([3.0, 2.8, 5.5], [2.0, 4.0, 5.0], "tied"),
        # one seed: +0.0% (the old report called this a win), +3% (inside 5%), +10% and -10%
        ([1.03e6], [1.03e6], "tied"),
        ([1.03], [1.0], "tied"),
        ([1.1], [1.0], "beat"),
        ([0.9], [1.0], "lost"),
    ],
)
def test_hv_verdict_with_a_tolerance(mapex_hv, warm_hv, outcome):
    runs = [_run("mapex", s, h) for s, h in enumerate(mapex_hv)] + [_run("warmup_only", s, h) for s, h in enumerate(warm_hv)]
    verdict = hv_verdict(runs)
    assert verdict.outcome == outcome
    verb = {"beat": "(MAPEX) beat", "lost": "(MAPEX) lost to", "tied": "(MAPEX) tied with"}[outcome]
    assert verb in verdict.sentence
    assert f"{len(mapex_hv)} seed" in verdict.sentence
    if len(mapex_hv) > 1:
        assert "± " in verdict.sentence and "paired difference" in verdict.sentence
    else:
        assert "one seed only" in verdict.sentence


def test_hv_verdict_min_difference_is_a_param():
    runs = [_run("mapex", 0, 1.03), _run("warmup_only", 0, 1.0)]
    assert hv_verdict(runs, min_difference=0.01).outcome == "beat"
    assert hv_verdict(runs, min_difference=0.05).outcome == "tied"


def test_hv_verdict_without_pairs():
    verdict = hv_verdict([_run("mapex", 0, 1.0), _run("warmup_only", 1, 2.0)])
    assert verdict.outcome == "unknown" and "Cannot say" in verdict.sentence


def test_report_replaces_old_report_and_refuses_foreign_folder(runs, tmp_path):
    out_dir = tmp_path / "rep"
    out_dir.mkdir()
    (out_dir / "report.md").write_text("old")
    (out_dir / "stale.png").write_bytes(b"x")
    args = ("report", "--evaluated", runs / "evaluate", "--extracted", runs / "extract", "--params", runs / "params.yaml")
    code, out = invoke(*args, "--out", out_dir)
    assert code == 0, out
    assert not (out_dir / "stale.png").exists() and (out_dir / "report.md").read_text() != "old"
    foreign = tmp_path / "data"
    foreign.mkdir()
    (foreign / "precious.txt").write_text("keep")
    code, out = invoke(*args, "--out", foreign)
    assert code == 2 and "refusing" in out and (foreign / "precious.txt").read_text() == "keep"


def test_report_bad_inputs(runs, tmp_path):
    params = runs / "params.yaml"
    code, out = invoke("report", "--evaluated", tmp_path, "--extracted", runs / "extract", "--out", tmp_path / "r",
                       "--params", params)
    assert code == 2 and "no VARIANT/seedS/metrics.json" in out
    code, out = invoke("report", "--evaluated", runs / "evaluate", "--extracted", tmp_path / "nothing",
                       "--out", tmp_path / "r", "--params", params)
    assert code == 2 and "history.csv" in out and "not found" in out
    assert not (tmp_path / "r").exists()


def test_sparsity_in_report_is_finite(runs):
    for v in VARIANTS:
        m = json.loads((runs / "evaluate" / v / "seed0" / "metrics.json").read_text())
        assert all(isinstance(x, (int, float)) and math.isfinite(x) for x in m["front"].values())


# ---------------------------------------------------------------- reference points

REPO = Path(__file__).resolve().parents[1]


def test_reference_point_presets_match_params_and_doc():
    presets = yaml.safe_load((REPO / "presets" / "reference_points.yaml").read_text())
    from pipeline.envs import OBJECTIVE_NAMES

    assert set(presets) == set(OBJECTIVE_NAMES)
    doc = (REPO / "docs" / "reference_points.md").read_text()
    for env_id, ref in presets.items():
        assert len(ref) == 2 and all(isinstance(x, float) for x in ref)
        assert f"| {env_id} |" in doc and f"[{ref[0]:g}, {ref[1]:g}]" in doc
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    assert params["env"]["reference_point"] == presets[params["env"]["id"]]


def test_halfcheetah_energy_bound_is_attained_by_saturated_actions():
    """-sum(a^2) per step: -6 with |a| = 1 in all 6 dims, so 750 steps give the -4500 reference."""
    env = make_env(ENV_ID, 10)
    env.reset(seed=0)
    total = sum(env.step(np.array([1.0, -1.0] * 3))[1][1] for _ in range(10))
    assert total == pytest.approx(-60.0)
    env.reset(seed=0)
    assert sum(env.step(np.full(6, 0.5))[1][1] for _ in range(10)) == pytest.approx(-15.0)


def test_report_with_one_variant_one_seed(runs, tmp_path):
    import shutil

    shutil.copytree(runs / "evaluate" / "mapex" / "seed1", tmp_path / "ev" / "mapex" / "seed1")
    code, out = invoke("report", "--evaluated", tmp_path / "ev", "--extracted", runs / "extract",
                       "--out", tmp_path / "rep", "--params", runs / "params.yaml")
    assert code == 0, out
    text = (tmp_path / "rep" / "report.md").read_text()
    assert "Cannot say whether" in text and "(one seed: no SEM)" in text
    assert sorted(p.name for p in (tmp_path / "rep").iterdir()) == ["front_seed1.png", "hypervolume.png", "report.md"]


def test_report_ignores_seeds_params_does_not_list(runs, tmp_path):
    params = yaml.safe_load((runs / "params.yaml").read_text())
    params["seeds"] = [1]
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    r = CliRunner().invoke(app, ["report", "--evaluated", str(runs / "evaluate"), "--extracted", str(runs / "extract"),
                                 "--out", str(tmp_path / "rep"), "--params", str(tmp_path / "params.yaml")])
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in (tmp_path / "rep").glob("front_seed*.png")) == ["front_seed1.png"]
