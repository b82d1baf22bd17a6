"""Stages evaluate, score and report end to end through their real typer commands, on tiny
synthetic populations (random [16, 16] actors on HalfCheetah, 50-step episodes, 2 episodes a
member), with the provenance records the stages write beside their outputs; the verdict and
provenance table on hand-made runs. The score stage's known answers are in test_score.py."""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import typer
import yaml
from typer.testing import CliRunner

from pipeline.core.envs import make_env
from pipeline.core.nets import Actor
from pipeline.core.population import Member, actor_state, load_population, member_actor, save_population
from pipeline.evaluation.episodes import eval_seeds, evaluate_policy
from pipeline.evaluation.metrics import hypervolume, mean_sem
from pipeline.params import section
from pipeline.params.report import ReportParams
from pipeline.params.variants import is_hybrid
from pipeline.reporting.cost import verdict_cost_table
from pipeline.reporting.presentation import specialist_kind, use_variants
from pipeline.reporting.runs import Run, load_runs
from pipeline.reporting.specialists import own_returns_table, sources_line, weak_sentence, weak_specialists
from pipeline.reporting.tables import (
    fmt_num,
    frames_to_reach,
    provenance_table,
    sample_efficiency_table,
    specialist_groups,
    specialist_metrics,
)
from pipeline.reporting.verdicts import hv_verdict, verdict_outcome, verdicts
from stages.evaluate import evaluate
from stages.grid_report import grid_report
from stages.report import report
from stages.score import score

ENV_ID = "mo-halfcheetah-v5"
REF = [-100.0, -4500.0]
CAP = 50
EPISODES = 2
SEEDS = (0, 1)
VARIANTS = ("mapex_td3", "warmup_only_td3")
PROVENANCE = {
    "git_commit": "0123456789abcdef",
    "git_dirty": False,
    "device": "cpu: test",
    "torch_threads": 1,
    "versions": {"torch": "2.13.0", "numpy": "2.4", "mujoco": "4.0", "gymnasium": "1.4", "mo-gymnasium": "1.3.2"},
}


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


def make_population(path: Path, seed: int, variant: str, env_id: str = ENV_ID, drop: tuple[str, ...] = ()) -> None:
    """2 specialists (the same for every variant of a seed, as in a real run) + 3 children."""
    low, high = [-1.0] * 6, [1.0] * 6
    members = []
    for i in range(5):
        specialist = i < 2
        torch.manual_seed(1000 * seed + i + (0 if specialist or variant == "mapex_td3" else 100))
        actor = Actor(17, 6, [16, 16], low, high)
        members.append(
            Member(
                origin="specialist" if specialist else "child",
                objective=i if specialist else None,
                iteration=0 if specialist else i - 1,
                parents=[] if specialist else [0, 1],
                target_weight=None if specialist else [0.6, 0.8],
                returns=[float(10 * i - 20), float(-100 * i)],
                returns_std=[1.0, 2.0],
                eval_episodes=5,
                env_samples=250 * (i + 1),
                hidden_sizes=[16, 16],
                actor=actor_state(actor),
                policy_name="policy" if specialist else None,
            )
        )
    meta = dict(
        env_id=env_id,
        obs_dim=17,
        act_dim=6,
        n_objectives=2,
        action_low=low,
        action_high=high,
        seed=seed,
        params={},
        method=variant,
    )
    save_population(path, members, {k: v for k, v in meta.items() if k not in drop})


def _app() -> typer.Typer:
    """The scoring commands as `mapex` runs them (stages.cli registers them)."""
    app = typer.Typer()

    @app.callback()
    def main() -> None:
        torch.set_num_threads(1)  # what `mapex` does with MAPEX_TORCH_THREADS unset

    for name, fn in (("evaluate", evaluate), ("score", score), ("report", report), ("grid-report", grid_report)):
        app.command(name)(fn)
    return app


APP = _app()


def invoke(*args) -> tuple[int, str]:
    result = CliRunner().invoke(APP, [str(a) for a in args])
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        raise result.exception
    return result.exit_code, result.output


def read_csv(path: Path) -> list[dict[str, str]]:
    import csv

    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def evaluate_and_score(root: Path, variant: str, seed: int, params: Path) -> None:
    """The evaluate and score stages of one run, each writing its provenance record under
    ROOT/provenance as dvc.yaml has them do under data/provenance."""
    pop = root / "extract" / variant / f"seed{seed}" / "population.pt"
    code, out = invoke(
        "evaluate",
        "--population",
        pop,
        "--out",
        root / "evaluate" / variant / f"seed{seed}",
        "--seed",
        seed,
        "--params",
        params,
        "--provenance",
        root / "provenance" / "evaluate" / variant / f"seed{seed}.json",
    )
    assert code == 0, out
    code, out = invoke(
        "score",
        "--population",
        pop,
        "--evaluated",
        root / "evaluate" / variant / f"seed{seed}",
        "--out",
        root / "score" / variant / f"seed{seed}",
        "--params",
        params,
        "--provenance",
        root / "provenance" / "score" / variant / f"seed{seed}.json",
    )
    assert code == 0, out


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> Path:
    """Populations, evaluate and score outputs for 2 seeds x 2 variants. Seed 0's populations
    come with an extraction record (PROVENANCE), seed 1's with none (extracted by hand, without
    --provenance)."""
    root = tmp_path_factory.mktemp("runs")
    params = write_params(root)
    for v in VARIANTS:
        for s in SEEDS:
            make_population(root / "extract" / v / f"seed{s}" / "population.pt", s, v)
            if s == 0:
                record = root / "provenance" / "fronts" / v / f"seed{s}.json"
                record.parent.mkdir(parents=True, exist_ok=True)
                record.write_text(json.dumps({"stage": "extract", **PROVENANCE}))
            evaluate_and_score(root, v, s, params)
    return root


# ---------------------------------------------------------------- evaluate


def test_evaluated_csv_rows_and_columns(runs):
    rows = read_csv(runs / "evaluate" / "mapex_td3" / "seed0" / "evaluated.csv")
    assert list(rows[0]) == [
        "id",
        "origin",
        "objective",
        "policy_name",
        "iteration",
        "parents",
        "env_samples",
        "obj0_extract",
        "obj1_extract",
        "obj0",
        "obj1",
        "obj0_std",
        "obj1_std",
    ]
    assert [r["id"] for r in rows] == ["0", "1", "2", "3", "4"]
    assert [r["origin"] for r in rows] == ["specialist"] * 2 + ["child"] * 3
    assert [r["policy_name"] for r in rows] == ["policy"] * 2 + [""] * 3
    members, _ = load_population(runs / "extract" / "mapex_td3" / "seed0" / "population.pt")
    for r, m in zip(rows, members):  # extraction-time record carried over unchanged
        assert [float(r["obj0_extract"]), float(r["obj1_extract"])] == m.returns
        assert (int(r["iteration"]), int(r["env_samples"]), r["parents"]) == (
            m.iteration,
            m.env_samples,
            ";".join(map(str, m.parents)),
        )
        assert float(r["obj0_std"]) >= 0 and float(r["obj1_std"]) >= 0


def test_evaluation_json(runs):
    record = json.loads((runs / "evaluate" / "mapex_td3" / "seed0" / "evaluation.json").read_text())
    assert (record["env_id"], record["method"], record["seed"], record["population"]) == (ENV_ID, "mapex_td3", 0, 5)
    assert (record["episodes"], record["seed_stream"], record["max_episode_steps"]) == (EPISODES, 1, CAP)
    assert record["env_samples_evaluation"] == 5 * EPISODES * CAP  # HalfCheetah never terminates
    assert "provenance" not in record  # a file of its own, outside OUT
    prov = json.loads((runs / "provenance" / "evaluate" / "mapex_td3" / "seed0.json").read_text())
    assert prov["stage"] == "evaluate" and prov["versions"]["torch"] == torch.__version__
    assert prov["torch_threads"] == 1 and prov["device"].startswith("cpu")


def test_reevaluation_uses_the_fresh_seed_stream(runs):
    """Member 2 re-evaluated by hand on stream 1 reproduces the CSV; stream 0 (extraction's) does not."""
    members, meta = load_population(runs / "extract" / "mapex_td3" / "seed1" / "population.pt")
    envs = [make_env(ENV_ID, CAP) for _ in range(EPISODES)]
    fresh = evaluate_policy(member_actor(members[2], meta), envs, eval_seeds(1, 1, 2, EPISODES)).mean
    old = evaluate_policy(member_actor(members[2], meta), envs, eval_seeds(1, 0, 2, EPISODES)).mean
    row = read_csv(runs / "evaluate" / "mapex_td3" / "seed1" / "evaluated.csv")[2]
    np.testing.assert_allclose([float(row["obj0"]), float(row["obj1"])], fresh, rtol=1e-6)
    assert not np.allclose(fresh, old)


def test_evaluate_is_deterministic_and_needs_no_reference_point(runs, tmp_path):
    params = write_params(tmp_path, env={"reference_point": None})
    code, out = invoke(
        "evaluate",
        "--population",
        runs / "extract" / "mapex_td3" / "seed0" / "population.pt",
        "--out",
        tmp_path / "again",
        "--seed",
        0,
        "--params",
        params,
    )
    assert code == 0, out
    for name in ("evaluated.csv", "evaluation.json"):
        assert (tmp_path / "again" / name).read_text() == (runs / "evaluate" / "mapex_td3" / "seed0" / name).read_text()


@pytest.mark.parametrize("processes,start", [(2, "fork"), (3, "fork"), (2, "spawn")])
def test_evaluate_in_worker_processes_writes_the_same_bytes(runs, tmp_path, monkeypatch, processes, start):
    """evaluate.processes > 1 deals the members to worker processes (forked with one torch thread,
    spawned where fork is not available): each member's episodes are the ones the stage's own loop
    runs, so evaluated.csv and evaluation.json are byte for byte those of one process."""
    import stages.evaluate as evaluate_stage

    if start == "spawn":  # as on a platform without fork
        monkeypatch.setattr(evaluate_stage.mp, "get_all_start_methods", lambda: ["spawn"])
    used = []
    real = evaluate_stage.run_parts
    monkeypatch.setattr(
        evaluate_stage, "run_parts", lambda *a, **k: used.append((len(a[1]), k["start"])) or real(*a, **k)
    )
    params = write_params(tmp_path, evaluate={"processes": processes})
    population = runs / "extract" / "mapex_td3" / "seed0" / "population.pt"
    code, out = invoke(
        "evaluate", "--population", population, "--out", tmp_path / "out", "--seed", 0, "--params", params
    )
    assert code == 0, out
    assert used == [(processes, start)]
    for name in ("evaluated.csv", "evaluation.json"):
        assert (tmp_path / "out" / name).read_bytes() == (runs / "evaluate" / "mapex_td3" / "seed0" / name).read_bytes()


def _evaluate_fails(tmp_path: Path, population: Path, params: Path, seed: int = 0) -> str:
    out_dir = tmp_path / "out"
    code, out = invoke("evaluate", "--population", population, "--out", out_dir, "--seed", seed, "--params", params)
    assert code == 2, out
    assert out.startswith("error: ") and "Traceback" not in out
    assert not out_dir.exists(), "nothing may be written on bad input"
    return out


def test_evaluate_missing_population(tmp_path):
    out = _evaluate_fails(tmp_path, tmp_path / "nope.pt", write_params(tmp_path))
    assert "nope.pt" in out and "not found" in out


def test_evaluate_truncated_population(tmp_path):
    good = tmp_path / "good.pt"
    make_population(good, 0, "mapex_td3")
    bad = tmp_path / "truncated.pt"
    bad.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    out = _evaluate_fails(tmp_path, bad, write_params(tmp_path))
    assert "truncated.pt" in out


@pytest.mark.parametrize("key", ["method", "seed", "action_low", "n_objectives"])
def test_evaluate_population_metadata_key_missing(tmp_path, key):
    pop = tmp_path / "pop.pt"
    make_population(pop, 0, "mapex_td3", drop=(key,))
    out = _evaluate_fails(tmp_path, pop, write_params(tmp_path))
    assert "pop.pt" in out and f"'{key}'" in out and len(out.strip().splitlines()) == 1


def test_evaluate_env_mismatch(tmp_path):
    pop = tmp_path / "swimmer.pt"
    make_population(pop, 0, "mapex_td3", env_id="mo-swimmer-v5")
    out = _evaluate_fails(tmp_path, pop, write_params(tmp_path))
    assert "swimmer.pt" in out and "mo-swimmer-v5" in out and ENV_ID in out


def test_evaluate_seed_mismatch(tmp_path):
    pop = tmp_path / "pop.pt"
    make_population(pop, 0, "mapex_td3")
    out = _evaluate_fails(tmp_path, pop, write_params(tmp_path), seed=3)
    assert "pop.pt" in out and "seed" in out


def test_evaluate_rejects_extraction_stream(tmp_path):
    pop = tmp_path / "pop.pt"
    make_population(pop, 0, "mapex_td3")
    out = _evaluate_fails(tmp_path, pop, write_params(tmp_path, evaluate={"seed_stream": 0}))
    assert "evaluate.seed_stream" in out


def test_evaluate_rejects_scoring_params(tmp_path):
    """distinct_tol and utility_weights moved to the `score` section."""
    pop = tmp_path / "pop.pt"
    make_population(pop, 0, "mapex_td3")
    out = _evaluate_fails(tmp_path, pop, write_params(tmp_path, evaluate={"distinct_tol": 0.02}))
    assert "evaluate.distinct_tol" in out and "unknown key" in out


# ---------------------------------------------------------------- score on real evaluations


def test_score_consistent_with_evaluated_csv(runs):
    metrics = json.loads((runs / "score" / "mapex_td3" / "seed0" / "metrics.json").read_text())
    rows = read_csv(runs / "evaluate" / "mapex_td3" / "seed0" / "evaluated.csv")
    means = np.array([[float(r["obj0"]), float(r["obj1"])] for r in rows])
    front_ids = [int(r["id"]) for r in read_csv(runs / "score" / "mapex_td3" / "seed0" / "front.csv")]
    assert metrics["front"]["hypervolume"] == pytest.approx(hypervolume(means, REF))
    assert metrics["front"]["hypervolume"] == pytest.approx(hypervolume(means[front_ids], REF))
    assert metrics["specialists"]["hypervolume"] == pytest.approx(hypervolume(means[:2], REF))
    extract = np.array([[float(r["obj0_extract"]), float(r["obj1_extract"])] for r in rows])
    assert metrics["extraction_hypervolume"] == pytest.approx(hypervolume(extract, REF))
    assert metrics["env_samples_evaluation"] == 5 * EPISODES * CAP and metrics["episodes"] == EPISODES
    history = read_csv(runs / "score" / "mapex_td3" / "seed0" / "hypervolume.csv")
    assert float(history[-1]["hypervolume"]) == pytest.approx(metrics["front"]["hypervolume"])
    assert float(history[-1]["hypervolume_extract"]) == pytest.approx(metrics["extraction_hypervolume"])
    assert all(isinstance(x, (int, float)) and math.isfinite(x) for x in metrics["front"].values())


def test_specialists_score_the_same_in_both_variants(runs):
    a = json.loads((runs / "score" / "mapex_td3" / "seed0" / "metrics.json").read_text())
    b = json.loads((runs / "score" / "warmup_only_td3" / "seed0" / "metrics.json").read_text())
    # hv_fraction and distinct_count are relative to each run's own [reference, ideal] box
    for key in ("hypervolume", "sparsity", "sparsity_pgmorl", "expected_utility", "cardinality"):
        assert a["specialists"][key] == b["specialists"][key]
    assert a["front"] != b["front"]  # the children differ


def test_provenance_records_lie_outside_the_outputs(runs):
    """Each stage's record is the --provenance file; its output folder holds no run-dependent file."""
    for v in VARIANTS:
        for s in SEEDS:
            for stage in ("evaluate", "score"):
                record = json.loads((runs / "provenance" / stage / v / f"seed{s}.json").read_text())
                assert record["stage"] == stage and record["versions"]["torch"] == torch.__version__
            assert sorted(p.name for p in (runs / "evaluate" / v / f"seed{s}").iterdir()) == [
                "evaluated.csv",
                "evaluation.json",
            ]
            assert sorted(p.name for p in (runs / "score" / v / f"seed{s}").iterdir()) == [
                "front.csv",
                "hypervolume.csv",
                "metrics.json",
            ]


# ---------------------------------------------------------------- report


def report_args(
    runs: Path,
    out: Path,
    params: Path | None = None,
    scored: Path | None = None,
    evaluated: Path | None = None,
    provenance: Path | None = None,
) -> list:
    return [
        "report",
        "--evaluated",
        evaluated or runs / "evaluate",
        "--scored",
        scored or runs / "score",
        "--provenance",
        provenance or runs / "provenance",
        "--out",
        out,
        "--params",
        params or runs / "params.yaml",
    ]


@pytest.fixture(scope="module")
def report_dir(runs) -> Path:
    code, out = invoke(*report_args(runs, runs / "report"))
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
    tables = [line for line in text.split("## Metrics", 1)[1].splitlines() if line.startswith("|")]
    header = tables[0].split("|")[1:-1]
    assert header[0].strip() == "Environment" and len(header) == 1 + 4 * 3
    assert any("Hypervolume" in h and "specialists only" in h for h in header)
    assert any("Sparsity (↓) MAPEX-TD3" in h for h in header)
    env_rows = [t for t in tables if t.startswith(f"| {ENV_ID} |")]
    assert len(env_rows) == 1
    assert all("±" in c for c in env_rows[0].split("|")[2:5])  # two seeds: mean ± SEM
    for variant in ("| MAPEX-TD3 |", "| warm-up only (TD3) |", "| TD3 specialists only |"):
        assert sum(t.startswith(variant) for t in tables) == 1
    assert "the paper reports hypervolume and sparsity" in text  # the added columns are not claimed as the paper's


def test_report_table_sparsity_is_the_papers(runs, report_dir):
    values = [
        json.loads((runs / "score" / "mapex_td3" / f"seed{s}" / "metrics.json").read_text())["front"]["sparsity"]
        for s in SEEDS
    ]
    mean, sem = mean_sem(values)
    row = next(t for t in (report_dir / "report.md").read_text().splitlines() if t.startswith(f"| {ENV_ID} |"))
    assert row.split("|")[5].strip() == f"{fmt_num(mean)} ± {fmt_num(sem)}"  # Sparsity (↓) MAPEX


def test_report_verdict_matches_numbers(runs, report_dir):
    hv = {
        v: [
            json.loads((runs / "score" / v / f"seed{s}" / "metrics.json").read_text())["front"]["hypervolume"]
            for s in SEEDS
        ]
        for v in VARIANTS
    }
    d = np.array(hv["mapex_td3"]) - np.array(hv["warmup_only_td3"])
    margin = 2 * d.std(ddof=1) / np.sqrt(len(d))
    majority = {1: (d > 0).sum() > 1, -1: (d < 0).sum() > 1}
    verb = (
        "beat"
        if d.mean() > margin and majority[1]
        else "lost to"
        if d.mean() < -margin and majority[-1]
        else "tied with"
    )
    text = (report_dir / "report.md").read_text()
    assert f"(MAPEX-TD3) {verb} warm-up only (TD3)" in text
    assert f"higher in {int((d > 0).sum())} of 2" in text
    dm, dsem = mean_sem(d)
    assert f"MAPEX-TD3 - warm-up only (TD3) = {fmt_num(dm)} ± {fmt_num(dsem)} (SEM" in text


def test_report_provenance_section(report_dir):
    text = (report_dir / "report.md").read_text()
    section = text.split("## Provenance", 1)[1].split("## Definitions", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("| ")][1:]
    extract = [r for r in rows if r.startswith("| extract |")]
    # seed 0's extractions left a record, seed 1's did not: two rows, each naming its runs
    assert len(extract) == 2
    assert "MAPEX-TD3 seed 0; warm-up only (TD3) seed 0" in extract[0] and "0123456789 |" in extract[0]
    assert "MAPEX-TD3 seed 1; warm-up only (TD3) seed 1" in extract[1] and "not recorded" in extract[1]
    # evaluate and score ran in this process for every run: one row each
    assert sum(r.startswith("| evaluate |") for r in rows) == 1 and sum(r.startswith("| score |") for r in rows) == 1
    assert torch.__version__ in section


def _provenance_rows(report_md: Path) -> list[str]:
    section = report_md.read_text().split("## Provenance", 1)[1].split("## Definitions", 1)[0]
    return [line for line in section.splitlines() if line.startswith("| ")][1:]


def test_report_without_provenance_records_says_not_recorded(runs, tmp_path):
    """Runs made without --provenance (or a report given no root): every stage 'not recorded',
    one row per stage, and the report is otherwise the same."""
    for where in (tmp_path / "no_records", None):
        args = report_args(runs, tmp_path / "r", provenance=where)
        if where is None:
            i = args.index("--provenance")
            del args[i : i + 2]
        code, out = invoke(*args)
        assert code == 0, out
        rows = _provenance_rows(tmp_path / "r" / "report.md")
        assert [r.split("|")[1].strip() for r in rows] == ["extract", "evaluate", "score"]
        assert all(r.endswith("|" + " not recorded |" * 8) for r in rows), rows


def test_report_names_an_unreadable_provenance_record(runs, tmp_path):
    shutil.copytree(runs / "provenance", tmp_path / "provenance")
    bad = tmp_path / "provenance" / "score" / "mapex_td3" / "seed1.json"
    bad.write_text("{not json")
    out = _report_fails(runs, tmp_path, provenance=tmp_path / "provenance")
    assert str(bad) in out and "cannot be read as JSON" in out


def _run(variant: str, seed: int, hv: float, provenance: dict | None = None) -> Run:
    metrics = {"front": {"hypervolume": hv}, "iterations": 4}
    empty = np.zeros(0)
    return Run(variant, seed, metrics, np.zeros((0, 2)), empty, empty, empty, {}, provenance)


def _runs(mapex_hv: list[float], warm_hv: list[float]) -> list[Run]:
    return [_run("mapex_td3", s, h) for s, h in enumerate(mapex_hv)] + [
        _run("warmup_only_td3", s, h) for s, h in enumerate(warm_hv)
    ]


def test_a_hybrid_run_against_warm_up_only_is_not_called_the_advantage_weighted_phase():
    """MAPEX run with extract.init: interpolate differs from warm-up only in its start and seeds
    too: the verdict names the method and its start, not 'the advantage-weighted phase'; the paper
    form's verdict keeps that name. Which methods are hybrids comes from the params (the report
    stage's use_variants, from pipeline.params.variants.is_hybrid), not from their metrics."""
    runs = _runs([3.0, 5.1, 7.9], [2.0, 4.0, 7.0])
    assert "the advantage-weighted phase (MAPEX-TD3) beat warm-up only" in hv_verdict(runs).sentence
    for r in runs[:3]:
        r.metrics["init_fallbacks"] = {}  # what the report used to guess from: no longer read
    assert "the advantage-weighted phase (MAPEX-TD3) beat warm-up only" in hv_verdict(runs).sentence
    raw = {"extract": {"init": "interpolate"}}
    use_variants({}, {m for m in ("mapex_td3", "warmup_only_td3") if is_hybrid(raw, m, {})})
    try:
        sentence = hv_verdict(runs).sentence
        assert "advantage-weighted" not in sentence, sentence
        assert "MAPEX-TD3, started from interpolated weights, beat warm-up only" in sentence, sentence
        # a pair given by name (report.pairs) is named by its label alone, as before
        assert "(3 seeds, up to 4 iterations), MAPEX-TD3 beat" in hv_verdict(runs, what="MAPEX-TD3").sentence
    finally:
        use_variants({})


def test_sources_line_names_the_imported_and_the_trained_objectives():
    """Runs whose metrics record specialist_sources (imported slots beside ones trained here) give one
    line naming both; runs without them give none."""
    sources = [
        {"objective": 0, "imported": {"format": "sb3", "algorithm": "sac", "file": "speed.zip"}},
        {"objective": 1, "trained": "td3", "total_steps": 60000},
    ]
    runs = [_run(m, s, 1.0) for m in ("mapex_posthoc_imported", "warmup_only_imported") for s in (0, 1)]
    assert sources_line(runs, ["x velocity", "energy"]) is None
    for r in runs:
        r.metrics["specialist_sources"] = sources
    assert sources_line(runs, ["x velocity", "energy"]) == (
        "objectives imported: 0 (x velocity: sb3 sac, file speed.zip); "
        "trained here: 1 (energy: TD3, 60000 steps with the td3 and train_specialist settings)"
    )
    for r in runs[1::2]:  # seed 1's specialist trained for another length
        r.metrics["specialist_sources"] = [sources[0], {**sources[1], "total_steps": 30000}]
    line = sources_line(runs, ["x velocity", "energy"])
    assert line.startswith("seed 0: objectives imported: 0") and "; seed 1: objectives imported" in line
    assert "30000 steps" in line and "60000 steps" in line


@pytest.mark.parametrize(
    "mapex_hv, warm_hv, outcome",
    [
        # 3 seeds, paired differences 1.0, 1.1, 0.9: mean 1.0, SEM 0.058 -> beyond 2 SEM, all higher: beat
        ([3.0, 5.1, 7.9], [2.0, 4.0, 7.0], "beat"),
        ([2.0, 4.0, 7.0], [3.0, 5.1, 7.9], "lost"),
        # differences +1, -1.2, +0.5: mean 0.1, SEM 0.65 -> inside the noise: tied, though 2 of 3 are higher
        ([3.0, 2.8, 5.5], [2.0, 4.0, 5.0], "tied"),
        # 3 seeds, every difference 0 (+0.0%): SEM 0 and mean 0 -> tied
        ([1.03e6, 2e6, 3e6], [1.03e6, 2e6, 3e6], "tied"),
        # one seed: +0.0% (the old report called this a win), +3% (inside 5%), +10% and -10%
        ([1.03e6], [1.03e6], "tied"),
        ([1.03], [1.0], "tied"),
        ([1.1], [1.0], "beat"),
        ([0.9], [1.0], "lost"),
    ],
)
def test_hv_verdict_with_a_tolerance(mapex_hv, warm_hv, outcome):
    verdict = hv_verdict(_runs(mapex_hv, warm_hv))
    assert verdict.outcome == outcome
    verb = {"beat": "(MAPEX-TD3) beat", "lost": "(MAPEX-TD3) lost to", "tied": "(MAPEX-TD3) tied with"}[outcome]
    assert verb in verdict.sentence
    n = len(mapex_hv)
    assert f"({n} seed{'s' if n > 1 else ''}," in verdict.sentence
    d = np.array(mapex_hv) - np.array(warm_hv)
    assert (
        f"MAPEX-TD3 was higher in {int((d > 0).sum())} of {n} seed(s), lower in {int((d < 0).sum())}"
        in verdict.sentence
    )
    if n > 1:  # mean ± SEM of each variant and of the paired differences, and the rule
        (am, asem), (bm, bsem), (dm, dsem) = mean_sem(mapex_hv), mean_sem(warm_hv), mean_sem(d)
        assert (
            f"MAPEX-TD3 {fmt_num(am)} ± {fmt_num(asem)}, warm-up only (TD3) {fmt_num(bm)} ± {fmt_num(bsem)}"
            in verdict.sentence
        )
        assert f"MAPEX-TD3 - warm-up only (TD3) = {fmt_num(dm)} ± {fmt_num(dsem)} (SEM" in verdict.sentence
        assert "beyond 2 SEM" in verdict.sentence and "more than half of the seeds" in verdict.sentence
    else:
        assert "One seed only" in verdict.sentence
        assert "within ±5% of warm-up only (TD3)'s hypervolume (report.min_difference)" in verdict.sentence
        assert f"{d[0] / warm_hv[0] * 100:+.1f}%" in verdict.sentence


def test_hv_verdict_min_difference_is_a_param():
    runs = _runs([1.03], [1.0])
    assert hv_verdict(runs, min_difference=0.01).outcome == "beat"
    assert hv_verdict(runs, min_difference=0.05).outcome == "tied"


def test_hv_verdict_noise_sems_is_a_param():
    runs = _runs([3.0, 5.1, 7.9], [2.0, 4.0, 7.0])  # mean 1.0, SEM 0.058: 17 SEM from zero
    assert hv_verdict(runs, noise_sems=10).outcome == "beat"
    assert hv_verdict(_runs([3.0, 5.3, 7.9], [2.0, 4.0, 7.0]), noise_sems=10).outcome == "tied"  # SEM 0.12: 8.9 SEM


def test_verdict_needs_a_majority_of_seeds():
    # differences 10, 10, -0.1, -0.1, -0.1: mean 3.94, SEM 2.47 -> beyond 1 SEM, but MAPEX higher in only 2 of 5
    d = np.array([10, 10, -0.1, -0.1, -0.1])
    assert verdict_outcome(d, np.ones(5), 0.05, noise_sems=1.0) == "tied"
    assert verdict_outcome(-d, np.ones(5), 0.05, noise_sems=1.0) == "tied"
    # 10, 10, 10, -0.1, -0.1: 3 of 5 higher, mean 5.96, SEM 2.47 -> beat
    assert verdict_outcome(np.array([10, 10, 10, -0.1, -0.1]), np.ones(5), 0.05, noise_sems=1.0) == "beat"


def test_hv_verdict_without_pairs():
    verdict = hv_verdict([_run("mapex_td3", 0, 1.0), _run("warmup_only_td3", 1, 2.0)])
    assert verdict.outcome == "unknown" and "Cannot say" in verdict.sentence


def test_provenance_table_groups_identical_rows():
    newer = {**PROVENANCE, "versions": {**PROVENANCE["versions"], "torch": "2.14.0"}, "git_dirty": True}
    runs = [
        _run("mapex_td3", 0, 1.0, {"extract": PROVENANCE}),
        _run("mapex_td3", 1, 1.0, {"extract": PROVENANCE}),
        _run("warmup_only_td3", 0, 1.0, {"extract": newer}),
        _run("warmup_only_td3", 1, 1.0, None),
    ]
    rows = [r for r in provenance_table(runs).splitlines() if r.startswith("| extract |")]
    assert rows == [
        "| extract | MAPEX-TD3 seeds 0, 1 | 0123456789 | 2.13.0 | 2.4 | 4.0 | 1.4 | 1.3.2 | cpu: test | 1 |",
        "| extract | warm-up only (TD3) seed 0 | 0123456789 (dirty) | 2.14.0 | 2.4 | 4.0 | 1.4 | 1.3.2 | cpu: test | 1 |",
        "| extract | warm-up only (TD3) seed 1 |" + " not recorded |" * 8,
    ]


def test_report_replaces_old_report_and_refuses_foreign_folder(runs, tmp_path):
    out_dir = tmp_path / "rep"
    out_dir.mkdir()
    (out_dir / "report.md").write_text("old")
    (out_dir / "stale.png").write_bytes(b"x")
    code, out = invoke(*report_args(runs, out_dir))
    assert code == 0, out
    assert not (out_dir / "stale.png").exists() and (out_dir / "report.md").read_text() != "old"
    foreign = tmp_path / "data"
    foreign.mkdir()
    (foreign / "precious.txt").write_text("keep")
    code, out = invoke(*report_args(runs, foreign))
    assert code == 2 and "refusing" in out and (foreign / "precious.txt").read_text() == "keep"


def _report_fails(runs: Path, tmp_path: Path, **kw) -> str:
    code, out = invoke(*report_args(runs, tmp_path / "r", **kw))
    assert code == 2, out
    assert out.startswith("error: ") and "Traceback" not in out and len(out.strip().splitlines()) == 1
    assert not (tmp_path / "r").exists()
    return out


def _copy_scored(runs: Path, tmp_path: Path) -> Path:
    scored = tmp_path / "score"
    shutil.copytree(runs / "score", scored)
    return scored


def test_report_without_score_outputs(runs, tmp_path):
    assert "no VARIANT/seedS/metrics.json" in _report_fails(runs, tmp_path, scored=tmp_path)


def test_report_without_evaluated_csv(runs, tmp_path):
    out = _report_fails(runs, tmp_path, evaluated=tmp_path / "nothing")
    assert "evaluated.csv" in out and "not found" in out


@pytest.mark.parametrize("name", ["front.csv", "hypervolume.csv"])
def test_report_missing_score_file(runs, tmp_path, name):
    scored = _copy_scored(runs, tmp_path)
    (scored / "mapex_td3" / "seed1" / name).unlink()
    out = _report_fails(runs, tmp_path, scored=scored)
    assert str(scored / "mapex_td3" / "seed1" / name) in out and "not found" in out


@pytest.mark.parametrize("key", ["episodes", "reference_point", "front.sparsity_pgmorl"])
def test_report_metrics_key_missing(runs, tmp_path, key):
    scored = _copy_scored(runs, tmp_path)
    path = scored / "warmup_only_td3" / "seed0" / "metrics.json"
    metrics = json.loads(path.read_text())
    group, _, leaf = key.rpartition(".")
    del (metrics[group] if group else metrics)[leaf]
    path.write_text(json.dumps(metrics))
    out = _report_fails(runs, tmp_path, scored=scored)
    assert str(path) in out and key in out


def test_report_history_column_missing(runs, tmp_path):
    scored = _copy_scored(runs, tmp_path)
    path = scored / "mapex_td3" / "seed0" / "hypervolume.csv"
    path.write_text("\n".join(",".join(line.split(",")[:-1]) for line in path.read_text().splitlines()) + "\n")
    out = _report_fails(runs, tmp_path, scored=scored)
    assert str(path) in out and "missing column(s) ['hypervolume']" in out


def test_report_refuses_mixed_reference_points(runs, tmp_path):
    scored = _copy_scored(runs, tmp_path)
    path = scored / "mapex_td3" / "seed1" / "metrics.json"
    path.write_text(json.dumps(json.loads(path.read_text()) | {"reference_point": [0.0, 0.0]}))
    assert "different reference points" in _report_fails(runs, tmp_path, scored=scored)


def test_report_refuses_a_run_in_the_wrong_folder(runs, tmp_path):
    scored = _copy_scored(runs, tmp_path)
    path = scored / "mapex_td3" / "seed1" / "metrics.json"
    path.write_text(json.dumps(json.loads(path.read_text()) | {"seed": 0}))
    out = _report_fails(runs, tmp_path, scored=scored)
    assert str(path) in out and "seed1" in out


def test_report_with_one_variant_one_seed(runs, tmp_path):
    shutil.copytree(runs / "score" / "mapex_td3" / "seed1", tmp_path / "sc" / "mapex_td3" / "seed1")
    code, out = invoke(*report_args(runs, tmp_path / "rep", scored=tmp_path / "sc"))
    assert code == 0, out
    text = (tmp_path / "rep" / "report.md").read_text()
    assert "No pair of comparable methods was run" in text and "(one seed: no SEM)" in text
    assert sorted(p.name for p in (tmp_path / "rep").iterdir()) == ["front_seed1.png", "hypervolume.png", "report.md"]


def test_report_ignores_seeds_params_does_not_list(runs, tmp_path):
    params = yaml.safe_load((runs / "params.yaml").read_text())
    params["seeds"] = [1]
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    code, out = invoke(*report_args(runs, tmp_path / "rep", params=tmp_path / "params.yaml"))
    assert code == 0, out
    assert sorted(p.name for p in (tmp_path / "rep").glob("front_seed*.png")) == ["front_seed1.png"]
    assert "seeds: 1\n" in (tmp_path / "rep" / "report.md").read_text()


# ---------------------------------------------------------------- reference points

REPO = Path(__file__).resolve().parents[1]


def test_report_says_where_the_reference_point_came_from(runs, report_dir, tmp_path, monkeypatch):
    """Scored with env.reference_point set, the report says so; rescored with it null, the
    point is the env's entry in presets/envs.yaml, and the report names that."""
    text = (report_dir / "report.md").read_text()
    assert "- hypervolume reference point: [-100.0, -4500.0] (from env.reference_point in params)\n" in text
    monkeypatch.chdir(REPO)  # the score stage reads presets/envs.yaml from the repository root
    params = write_params(tmp_path, env={"reference_point": None})
    for v in VARIANTS:
        for s in SEEDS:
            run_dir = f"seed{s}"
            code, out = invoke(
                "score",
                "--population",
                runs / "extract" / v / run_dir / "population.pt",
                "--evaluated",
                runs / "evaluate" / v / run_dir,
                "--out",
                tmp_path / "sc" / v / run_dir,
                "--params",
                params,
            )
            assert code == 0, out
            rescored = json.loads((tmp_path / "sc" / v / run_dir / "metrics.json").read_text())
            before = json.loads((runs / "score" / v / run_dir / "metrics.json").read_text())
            assert rescored["reference_point"] == REF and rescored["front"] == before["front"]
    code, out = invoke(*report_args(runs, tmp_path / "rep", scored=tmp_path / "sc"))
    assert code == 0, out
    line = (
        "- hypervolume reference point: [-100.0, -4500.0] (from presets/envs.yaml, "
        "entry mo-halfcheetah-v5 (env.reference_point is null))\n"
    )
    assert line in (tmp_path / "rep" / "report.md").read_text()


def test_reference_point_presets_match_params_and_doc():
    from pipeline.params.env_facts import read_facts, reference_points

    presets = reference_points()
    OBJECTIVE_NAMES = read_facts("objective_names")

    assert set(presets) == set(OBJECTIVE_NAMES)
    doc = (REPO / "docs" / "reference_points.md").read_text()
    for env_id, ref in presets.items():
        assert len(ref) == len(OBJECTIVE_NAMES[env_id]) and all(isinstance(x, float) for x in ref)
        assert f"| {env_id} |" in doc and "[" + ", ".join(f"{x:g}" for x in ref) + "]" in doc
    params = yaml.safe_load((REPO / "params.yaml").read_text())
    assert params["env"]["reference_point"] in (None, presets[params["env"]["id"]])


def test_halfcheetah_energy_bound_is_attained_by_saturated_actions():
    """-sum(a^2) per step: -6 with |a| = 1 in all 6 dims, so 750 steps give the -4500 reference."""
    env = make_env(ENV_ID, 10)
    env.reset(seed=0)
    total = sum(env.step(np.array([1.0, -1.0] * 3))[1][1] for _ in range(10))
    assert total == pytest.approx(-60.0)
    env.reset(seed=0)
    assert sum(env.step(np.full(6, 0.5))[1][1] for _ in range(10)) == pytest.approx(-15.0)


def _hist_run(method: str, seed: int, frames: list[float], hvs: list[float]) -> Run:
    """A run whose re-evaluated hypervolume history is `hvs` at cumulative `frames`; final HV = hvs[-1]."""
    r = _run(method, seed, hvs[-1])
    r.history = {"env_samples": np.asarray(frames, float), "hypervolume": np.asarray(hvs, float)}
    return r


def test_frames_to_reach_the_other_methods_final_hypervolume():
    # seed 0: MAPEX reaches MOPDERL's final 10 at 300 frames (50% = 5 at 200, 90% = 9 at 300)
    # seed 1: MAPEX never reaches MOPDERL's final 20 (tops out at 15: 50% at 100, 90% never)
    runs = [
        _hist_run("mapex_pderl", 0, [100, 200, 300], [1, 6, 12]),
        _hist_run("mopderl", 0, [500, 1000], [4, 10]),
        _hist_run("mapex_pderl", 1, [100, 200], [11, 15]),
        _hist_run("mopderl", 1, [500], [20]),
    ]
    reach = frames_to_reach(runs, "mapex_pderl", "mopderl")
    assert reach == {0.5: [200.0, 100.0], 0.9: [300.0, None], 1.0: [300.0, None]}
    back = frames_to_reach(runs, "mopderl", "mapex_pderl")  # MOPDERL vs MAPEX's final 12 and 15
    assert back == {0.5: [1000.0, 500.0], 0.9: [None, 500.0], 1.0: [None, 500.0]}
    table = sample_efficiency_table(runs)
    row = next(line for line in table.splitlines() if line.startswith("| MAPEX | MOPDERL |"))
    assert f"| {fmt_num(150.0)} ± {fmt_num(50.0)} |" in row  # 50%: mean of 200 and 100, SEM 50
    assert "300 (reached in 1 of 2 seeds)" in row
    assert sample_efficiency_table([_hist_run("mapex_td3", 0, [1], [1])]) == ""  # no MOPDERL: no table


def test_verdicts_cover_every_pair_that_ran_and_specialists_per_kind():
    runs = [
        _run(m, s, hv)
        for s in range(3)
        for m, hv in (
            ("mapex_pderl", 10.0 + s),
            ("warmup_only_pderl", 5.0 + s),
            ("mapex_td3", 7.0),
            ("mopderl", 10.0 + s),
        )
    ]
    found = [v.sentence.split(" on re-evaluated")[0].split("), ")[1] for v in verdicts(runs)]
    assert found == [
        "the advantage-weighted phase (MAPEX) beat warm-up only (PDERL)",
        "MAPEX (PDERL specialists) beat MAPEX-TD3",
        "MAPEX tied with MOPDERL",
    ]
    assert specialist_kind("mopderl") == "pderl" and specialist_kind("morld") is None
    assert specialist_kind("mapex_posthoc_td3") == "td3"
    for r in runs:
        r.metrics["specialists"] = {"hypervolume": {"pderl": 1.0, "td3": 2.0}[specialist_kind(r.method)]}
    assert specialist_groups(runs + [_run("morld", 0, 1.0)]) == ["specialists_pderl", "specialists_td3"]
    assert [m["hypervolume"] for m in specialist_metrics(runs, "td3")] == [2.0, 2.0, 2.0]
    assert [m["hypervolume"] for m in specialist_metrics(runs, "pderl")] == [1.0, 1.0, 1.0]


def test_grid_report_puts_every_cell_in_one_table(runs, tmp_path):
    """Two cell workspaces (as `mapex repro --ray` leaves them) -> one Table 1 row each, figures, provenance;
    a cell without scores is skipped and said so."""
    work = tmp_path / "sweeps" / "grid"
    for cell, seeds in (("cheetah.a", [0, 1]), ("cheetah.b", [1])):
        ws = work / cell
        (ws / "data").mkdir(parents=True)
        shutil.copytree(runs / "score", ws / "data" / "score")
        shutil.copytree(runs / "evaluate", ws / "data" / "evaluate")
        shutil.copytree(runs / "provenance", ws / "data" / "provenance")
        params = yaml.safe_load((runs / "params.yaml").read_text()) | {"seeds": seeds}
        # weak specialists by each cell's own report params: none in a, seed 1's speed specialist in b
        params["report"] |= (
            {"weak_specialist_fraction": None}
            if cell == "cheetah.a"
            else {"weak_specialist_fraction": None, "weak_specialist_min_return": [1e6, None]}
        )
        (ws / "params.yaml").write_text(yaml.safe_dump(params))
    (work / "unscored").mkdir()
    (work / "unscored" / "params.yaml").write_text((runs / "params.yaml").read_text())
    code, out = invoke("grid-report", work, "--out", tmp_path / "grid_report", "--dpi", "40")
    assert code == 0, out
    assert "skipped unscored: no data/score" in out
    text = (tmp_path / "grid_report" / "report.md").read_text()
    rows = [line for line in text.splitlines() if line.startswith("| cheetah.")]
    table = [r for r in rows if "(mo-halfcheetah-v5)" in r]
    assert [r.split("|")[1].strip() for r in table] == [
        "cheetah.a (mo-halfcheetah-v5)",
        "cheetah.b (mo-halfcheetah-v5)",
    ]
    hv = {
        s: json.loads((runs / "score" / "mapex_td3" / f"seed{s}" / "metrics.json").read_text())["front"]["hypervolume"]
        for s in (0, 1)
    }
    mean, sem = mean_sem([hv[0], hv[1]])
    assert table[0].split("|")[2].strip() == f"{fmt_num(mean)} ± {fmt_num(sem)}"  # Hypervolume MAPEX-TD3, both seeds
    assert table[1].split("|")[2].strip() == fmt_num(hv[1])  # cell b: seed 1 only
    assert "| cheetah.b | MAPEX-TD3 | 1 |" in text  # the seeds behind each cell
    weak = text.split("## Weak specialists", 1)[1].split("\n## ", 1)[0]
    (line,) = [line for line in weak.splitlines() if line.startswith("- ")]
    assert line.startswith("- cheetah.b: Warning: the TD3 x velocity specialist (objective 0) of seed 1 returned")
    extract_rows = [line for line in text.splitlines() if line.startswith("| cheetah.a | extract |")]
    # each cell's records from its data/provenance: seed 0's extractions recorded, seed 1's not
    assert len(extract_rows) == 2 and "0123456789 |" in extract_rows[0] and "not recorded" in extract_rows[1]
    assert all((tmp_path / "grid_report" / f).stat().st_size > 5000 for f in ("fronts.png", "hypervolume.png"))
    code, out = invoke("grid-report", tmp_path / "nothing_here", "--out", tmp_path / "x")
    assert code == 2 and "nothing_here: not a directory" in out


def _cross_cell(runs: Path, ws: Path, hv: dict[int, float], core_s: float, report: dict | None = None) -> None:
    """A cell workspace from the fixture's runs: MAPEX-TD3 of the seeds of `hv` (seed S copied
    from the fixture's seed min(S, 1)) with hypervolume hv[S] and an extraction record of
    `core_s` core-seconds, warm-up only of seeds 0 and 1 as they are."""
    for kind in ("score", "evaluate"):
        shutil.copytree(runs / kind / "warmup_only_td3", ws / "data" / kind / "warmup_only_td3")
    for s, value in hv.items():
        score = ws / "data" / "score" / "mapex_td3" / f"seed{s}"
        shutil.copytree(runs / "score" / "mapex_td3" / f"seed{min(s, 1)}", score)
        shutil.copytree(
            runs / "evaluate" / "mapex_td3" / f"seed{min(s, 1)}",
            ws / "data" / "evaluate" / score.parent.name / score.name,
        )
        metrics = json.loads((score / "metrics.json").read_text())
        metrics["seed"], metrics["front"]["hypervolume"] = s, value
        (score / "metrics.json").write_text(json.dumps(metrics))
        record = ws / "data" / "provenance" / "fronts" / "mapex_td3" / f"seed{s}.json"
        record.parent.mkdir(parents=True, exist_ok=True)
        record.write_text(json.dumps({"stage": "extract", "cost": {"cpu_seconds": core_s}}))
    params = yaml.safe_load((runs / "params.yaml").read_text()) | {"seeds": sorted({0, 1, *hv})}
    params["report"] |= report or {}
    (ws / "params.yaml").write_text(yaml.safe_dump(params))


def test_grid_report_verdict_across_cells_is_the_per_cell_verdict(runs, tmp_path):
    """--pair CELL.hybrid/mapex_td3,CELL.paper/mapex_td3: the verdict (sentence and cost row) the per-cell
    report's functions give on the same runs laid out as one cell (paper's MAPEX-TD3 posing as
    warm-up only (PDERL)), each method named with its cell; paired over seeds 0-2, seeds 3 and 4
    (one side each) left out and named."""
    work = tmp_path / "sweeps" / "frontmixed"
    hybrid, paper = "halfcheetah-mixed.hybrid", "halfcheetah-mixed.paper"  # the grid's cell names
    _cross_cell(runs, work / hybrid, {0: 110.0, 1: 120.0, 2: 130.0, 3: 50.0}, 100.0)
    _cross_cell(runs, work / paper, {0: 100.0, 1: 100.0, 2: 100.0, 4: 500.0}, 200.0)
    one = tmp_path / "one"  # the same numbers as one cell: paper's MAPEX-TD3 as a second method
    for side, method in ((hybrid, "mapex_td3"), (paper, "warmup_only_pderl")):
        for kind, sub in (("score", "score"), ("evaluate", "evaluate"), ("provenance", "provenance/fronts")):
            shutil.copytree(work / side / "data" / sub / "mapex_td3", one / sub / method)
        for metrics_path in (one / "score" / method).glob("seed*/metrics.json"):
            metrics_path.write_text(json.dumps(json.loads(metrics_path.read_text()) | {"method": method}))
    one_runs = load_runs(one / "score", one / "evaluate", one / "provenance")
    (per_cell,) = verdicts(one_runs, 0.05, 2.0, [["mapex_td3", "warmup_only_pderl"]])
    per_cell_costs = verdict_cost_table([per_cell], one_runs)
    names = {"MAPEX-TD3": f"MAPEX-TD3 [{hybrid}]", "warm-up only (PDERL)": f"MAPEX-TD3 [{paper}]"}

    def across(text: str) -> str:
        return re.sub(r"MAPEX-TD3|warm-up only \(PDERL\)", lambda m: names[m.group()], text)

    code, out = invoke(
        "grid-report",
        work,
        "--out",
        tmp_path / "report",
        "--dpi",
        "40",
        "--pair",
        f"{hybrid}/mapex_td3,{paper}/mapex_td3",
        "--pair",
        f"{paper}/mapex_td3 {hybrid}/warmup_only_td3",
    )
    assert code == 0, out
    text = (tmp_path / "report" / "report.md").read_text()
    section = text.split("## Verdicts across cells", 1)[1].split("\n## ", 1)[0]
    bullets = [line for line in section.splitlines() if line.startswith("- ")]
    assert per_cell.outcome == "beat" and "+20.0% of warm-up only (PDERL)'s mean" in per_cell.sentence
    assert "over seeds 0, 1, 2:" in per_cell.sentence  # seeds 3 (50) and 4 (500) unpaired
    assert bullets[0] == (
        f"- {across(per_cell.sentence)} Left out, unpaired: seed 3 (MAPEX-TD3 [{hybrid}] only), "
        f"seed 4 (MAPEX-TD3 [{paper}] only)."
    )
    assert bullets[1].startswith("- At this scale (2 seeds, ") and bullets[1].endswith(
        f"Left out, unpaired: seed 2 (MAPEX-TD3 [{paper}] only), seed 4 (MAPEX-TD3 [{paper}] only)."
    )
    assert f"MAPEX-TD3 [{paper}] lost to warm-up only (TD3) [{hybrid}] on re-evaluated" in bullets[1]
    per_cell_row = across(per_cell_costs.splitlines()[2])
    assert "| 0.5x |" in per_cell_row and per_cell_row in section.splitlines()


@pytest.mark.parametrize(
    ("pair", "report", "message"),
    [
        ("hybird/mapex_td3,paper/mapex_td3", None, "'hybird' is not a cell in"),
        ("unscored/mapex_td3,paper/mapex_td3", None, "'unscored' is not scored (no data/score) in"),
        ("hybrid/mapex_td3,paper/mapex_pderl", None, "cell paper of"),
        ("hybrid/mapex_td3", None, "expected CELL_A/METHOD_A,CELL_B/METHOD_B"),
        ("hybrid/mapex_td3,hybrid/mapex_td3", None, "compares mapex_td3 of cell hybrid with itself"),
        ("hybrid/mapex_td3,paper/mapex_td3", {"noise_sems": 3.0}, "have different report.noise_sems (2 and 3"),
    ],
)
def test_grid_report_pair_errors(runs, tmp_path, pair, report, message):
    work = tmp_path / "grid"
    _cross_cell(runs, work / "hybrid", {0: 1.0, 1: 2.0}, 1.0)
    _cross_cell(runs, work / "paper", {0: 1.0, 1: 2.0}, 1.0, report)
    (work / "unscored").mkdir()
    (work / "unscored" / "params.yaml").write_text((runs / "params.yaml").read_text())
    code, out = invoke("grid-report", work, "--out", tmp_path / "report", "--pair", pair)
    (line,) = [x for x in out.splitlines() if x.startswith("error: ")]
    assert code == 2 and message in line and not (tmp_path / "report").exists()
    if "is not" in message:
        assert line.endswith("(scored cells: hybrid, paper)")
    if "cell paper of" in message:
        assert line.endswith("has no scored run of method 'mapex_pderl' (its methods: mapex_td3, warmup_only_td3)")


# ---------------------------------------------------------------- weak specialists

NAMES = ["x velocity", "energy efficiency"]


def _spec_run(method: str, seed: int, starts: list[tuple[int, list[float]]], children=()) -> Run:
    """A run whose starting policies are `starts` ((objective of its specialist, returns) each),
    then `children` (returns each)."""
    returns = np.array([r for _, r in starts] + [list(c) for c in children], float).reshape(-1, 2)
    origin = np.array(["specialist"] * len(starts) + ["child"] * len(children))
    objective = np.array([k for k, _ in starts] + [-1] * len(children))
    n = len(origin)
    metrics = {"front": {"hypervolume": 1.0}, "iterations": 1}
    return Run(method, seed, metrics, returns, origin, np.zeros(n, int), np.zeros(n, bool), {}, None, objective)


def _td3(speeds: list[float], energies: list[float], methods=("mapex_td3", "warmup_only_td3")) -> list[Run]:
    """TD3 runs of seeds 0.. whose speed specialist returned speeds[s] on speed (-3000 on energy)
    and energy specialist energies[s] on energy (0 on speed); a child better at both that must not count."""
    return [
        _spec_run(m, s, [(0, [v, -3000.0 + s]), (1, [0.0, e])], children=[[5000.0, 0.0]])
        for m in methods
        for s, (v, e) in enumerate(zip(speeds, energies))
    ]


def test_own_returns_table_reads_one_run_per_seed_and_kind():
    runs = _td3([1754.0, 10.0], [-4.0, -6.0])
    # PDERL seed 0: MAPEX starts from the whole policy sets (3 policies each, best speed 900,
    # best energy -2); MOPDERL's populations hold fewer: the extraction run's numbers are the ones
    sets = [(0, [300.0, -2500.0]), (0, [900.0, -2900.0]), (0, [600.0, -2000.0])]
    sets += [(1, [5.0, -9.0]), (1, [1.0, -2.0]), (1, [2.0, -3.0])]
    runs += [_spec_run("mopderl", 0, sets[:1] + sets[3:4]), _spec_run("mapex_pderl", 0, sets)]
    runs += [_spec_run("morld", 0, [], children=[[1.0, 1.0]])]  # no specialists: no row
    table = own_returns_table(runs, NAMES)
    assert table.splitlines() == [
        "| specialists | seed | x velocity (objective 0) | energy efficiency (objective 1) |",
        "|---|---|---|---|",
        "| PDERL | 0 | 900 (best of 3) | -2 (best of 3) |",
        "| TD3 | 0 | 1754 | -4 |",
        "| TD3 | 1 | 10 | -6 |",
    ]
    assert own_returns_table([_spec_run("morld", 0, [], children=[[1.0, 1.0]])], NAMES) == ""


def test_weak_specialist_by_fraction_of_the_best_seed():
    runs = _td3([1754.0, 10.0, 877.0], [-4.0, -5.0, -6.0])  # 877 = exactly 50% of 1754: not below
    weak = weak_specialists(runs, fraction=0.5)
    assert [(w.own.kind, w.own.seed, w.own.objective) for w in weak] == [("td3", 1, 0)]
    assert weak_sentence(weak[0], NAMES) == (
        "Warning: the TD3 x velocity specialist (objective 0) of seed 1 returned 10 on its own objective, "
        "below 50% of the best TD3 seed's (1754, seed 0): fronts from it are not evidence about the method."
    )
    assert [w.own.seed for w in weak_specialists(runs, fraction=0.4)] == [1]
    assert [w.own.seed for w in weak_specialists(runs, fraction=0.6)] == [1, 2]
    assert weak_specialists(runs, fraction=None) == []
    assert weak_specialists(_td3([1754.0, 1000.0], [-4.0, -5.0]), fraction=0.5) == []  # nothing weak
    assert weak_specialists(_td3([10.0], [-4.0]), fraction=0.5) == []  # one seed: it is its own best
    table = own_returns_table(runs, NAMES, weak)
    assert "| TD3 | 1 | 10 (weak) | -5 |" in table and "| TD3 | 2 | 877 | -6 |" in table
    # a policy set is judged by its best policy, and the sentence says so
    sets = {s: [(0, [v, -3000.0]), (0, [v / 2, -3000.0]), (1, [0.0, -4.0])] for s, v in ((0, 1000.0), (1, 100.0))}
    pderl = [_spec_run("mapex_pderl", s, p) for s, p in sets.items()]
    (w,) = weak_specialists(pderl, fraction=0.5)
    assert weak_sentence(w, NAMES).startswith(
        "Warning: the PDERL x velocity specialist (objective 0) of seed 1, its best of 2 policies, returned 100 on"
    )


def test_weak_specialist_by_absolute_return():
    runs = _td3([1754.0, 60.0], [-4.0, -5.0])
    assert weak_specialists(runs, fraction=None, min_return=[None, None]) == []
    assert weak_specialists(runs, fraction=None, min_return=[50.0, None]) == []
    (w,) = weak_specialists(runs, fraction=None, min_return=[100.0, None])
    assert (w.own.seed, w.own.objective) == (1, 0)
    assert "returned 60 on its own objective, below report.weak_specialist_min_return (100):" in weak_sentence(w, NAMES)
    # energy efficiency below -4.5: seed 1; both rules failing are both said
    weak = weak_specialists(runs, fraction=0.5, min_return=[100.0, -4.5])
    assert [(w.own.seed, w.own.objective) for w in weak] == [(1, 0), (1, 1)]
    assert "below 50% of the best TD3 seed's (1754, seed 0) and below report.weak_specialist_min_return (100)" in (
        weak_sentence(weak[0], NAMES)
    )
    assert weak_specialists(_td3([10.0], [-4.0]), fraction=0.5, min_return=[100.0, None])[0].own.seed == 0


def test_weak_specialist_on_an_objective_whose_best_is_negative():
    # energy: best seed -4; a fraction of -4 (-2) would flag every seed. The worst starting policy
    # on energy is seed 0's speed specialist (-3000), so the threshold is -3000 + 0.5 * 2996 = -1502
    runs = _td3([1000.0, 1000.0, 1000.0], [-4.0, -1000.0, -2004.0])
    weak = weak_specialists(runs, fraction=0.5)
    assert [(w.own.seed, w.own.objective) for w in weak] == [(2, 1)]
    assert weak_sentence(weak[0], NAMES) == (
        "Warning: the TD3 energy efficiency specialist (objective 1) of seed 2 returned -2004 on its own "
        "objective, below -1502, 50% of the way up from the worst starting policy's return (-3000) to the best "
        "TD3 seed's (-4, seed 0): fronts from it are not evidence about the method."
    )
    # every seed the same: nothing below the best, whatever its sign
    assert weak_specialists(_td3([1.0, 1.0], [-4.0, -4.0]), fraction=1.0) == []
    # a best of exactly 0 takes the range rule too (0.5 * 0 = 0 would flag seeds 1 and 2): the worst
    # on speed is seed 2's -10, so the threshold is -10 + 0.5 * 10 = -5
    weak = weak_specialists(_td3([0.0, -4.0, -10.0], [-4.0, -4.0, -4.0]), fraction=0.5)
    assert [(w.own.seed, w.own.objective) for w in weak] == [(2, 0)]


def test_report_states_specialists_own_returns_and_warns(runs, report_dir, tmp_path):
    text = (report_dir / "report.md").read_text()
    section = text.split("## Specialists on their own objectives", 1)[1].split("## Metrics", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("| TD3 |")]
    for s, row in zip(SEEDS, rows):  # every method of a seed starts from the same ones: read from one
        members = read_csv(runs / "evaluate" / "warmup_only_td3" / f"seed{s}" / "evaluated.csv")
        own = [fmt_num(float(next(m for m in members if m["objective"] == str(k))[f"obj{k}"])) for k in range(2)]
        assert [c.strip().removesuffix(" (weak)") for c in row.split("|")[1:-1]] == ["TD3", str(s), *own]
    params = yaml.safe_load((runs / "params.yaml").read_text())
    params["report"] |= {"weak_specialist_fraction": None, "weak_specialist_min_return": [1e6, None]}
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    code, out = invoke(*report_args(runs, tmp_path / "rep", params=tmp_path / "params.yaml"))
    assert code == 0, out
    text = (tmp_path / "rep" / "report.md").read_text()
    verdicts_section = text.split("## Verdicts", 1)[1].split("\n## ", 1)[0]
    warnings = [line for line in verdicts_section.splitlines() if line.startswith("- Warning:")]
    assert [w.split(" specialist")[0] for w in warnings] == ["- Warning: the TD3 x velocity"] * 2
    assert all("below report.weak_specialist_min_return (1.00e6)" in w for w in warnings)
    assert text.count(" (weak) |") == 2


@pytest.mark.parametrize(
    "key, value, expected",
    [
        ("weak_specialist_fraction", 0, "report.weak_specialist_fraction = 0: Input should be greater than 0"),
        ("weak_specialist_fraction", 1.5, "report.weak_specialist_fraction = 1.5: Input should be less than or"),
        ("weak_specialist_min_return", 100, "report.weak_specialist_min_return = 100: Input should be a valid list"),
        ("weak_specialist_min_return", ["x"], "report.weak_specialist_min_return.0 = 'x': Input should be a valid"),
        ("weak_specialist_min_return", [], "report.weak_specialist_min_return = []: List should have at least 1"),
        ("weak_specialist_min_return", [1.0, None, 2.0], "report.weak_specialist_min_return = [1.0, None, 2.0]: "),
    ],
)
def test_report_rejects_bad_weak_specialist_params(runs, tmp_path, key, value, expected):
    params = yaml.safe_load((runs / "params.yaml").read_text())
    params["report"][key] = value
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(params))
    code, out = invoke(*report_args(runs, tmp_path / "rep", params=tmp_path / "params.yaml"))
    assert code == 2 and expected in out, out
    assert not (tmp_path / "rep").exists()


def test_weak_specialist_params_defaults_and_accepted_values():
    p = ReportParams()
    assert (p.weak_specialist_fraction, p.weak_specialist_min_return) == (0.5, None)
    p = section(
        {"report": {"weak_specialist_fraction": None, "weak_specialist_min_return": [100, None]}},
        "report",
        ReportParams,
    )
    assert (p.weak_specialist_fraction, p.weak_specialist_min_return) == (None, [100.0, None])
    assert section({"report": {"weak_specialist_fraction": 1}}, "report", ReportParams).weak_specialist_fraction == 1


# ---------------------------------------------------------------- what each front cost


def _cost_rows(iterations: list[int], per_iteration: float) -> list[dict]:
    """Per-iteration cost rows (pipeline.core.cost.COST_FIELDS): the start, then one per iteration,
    each `per_iteration` core-seconds, a quarter of it evaluating."""
    rows = [
        {
            "iteration": 0,
            "phase": "start",
            "policies": 2,
            "train_wall_s": 0.0,
            "train_cpu_s": 0.0,
            "eval_wall_s": 1.0,
            "eval_cpu_s": 1.0,
        }
    ]
    for it in iterations:
        rows.append(
            {
                "iteration": it,
                "phase": "children",
                "policies": 1,
                "train_wall_s": 0.75 * per_iteration,
                "train_cpu_s": 0.75 * per_iteration,
                "eval_wall_s": 0.25 * per_iteration,
                "eval_cpu_s": 0.25 * per_iteration,
            }
        )
    return rows


def test_report_puts_a_cost_column_beside_every_verdict_and_draws_hypervolume_against_core_seconds(runs, tmp_path):
    """With cost records (the extract stage's per-iteration rows, the specialists' process seconds),
    the report has a cost table, a cost column beside the verdict and cost.png; each method's
    core-seconds are the sum of its rows, and the figure's curve ends at that sum."""
    from pipeline.reporting.cost import cost_curve, method_core_seconds
    from pipeline.reporting.figures import cost_figure
    from pipeline.reporting.runs import load_runs

    root = tmp_path / "runs"
    shutil.copytree(runs, root)
    its = sorted(
        {
            int(line.split(",")[0])
            for line in (root / "score" / "mapex_td3" / "seed0" / "hypervolume.csv").read_text().splitlines()[1:]
        }
        - {0}
    )
    per = {"mapex_td3": 100.0, "warmup_only_td3": 10.0}  # core-seconds per iteration
    for v in VARIANTS:
        for s in SEEDS:
            record = root / "provenance" / "fronts" / v / f"seed{s}.json"
            record.parent.mkdir(parents=True, exist_ok=True)
            cost = {"cpu_seconds": 999.0, "wall_seconds": 500.0, "iterations": _cost_rows(its, per[v] * (1 + s))}
            record.write_text(json.dumps({"stage": "extract", **PROVENANCE, "cost": cost}))
    for s in SEEDS:
        spec = root / "provenance" / "specialists" / "td3" / f"seed{s}.json"
        spec.parent.mkdir(parents=True, exist_ok=True)
        spec.write_text(json.dumps({"stage": "train_specialist", **PROVENANCE, "cost": {"cpu_seconds": 3000.0 + s}}))
    code, out = invoke(*report_args(root, tmp_path / "report", provenance=root / "provenance"))
    assert code == 0, out
    text = (tmp_path / "report" / "report.md").read_text()
    total = {v: [1.0 + per[v] * (1 + s) * len(its) for s in SEEDS] for v in VARIANTS}
    mean = {v: float(np.mean(total[v])) for v in VARIANTS}
    # the cost column beside the verdict
    verdicts_part = text.split("## Verdicts", 1)[1].split("## ", 1)[0]
    row = next(line for line in verdicts_part.splitlines() if line.startswith("| MAPEX-TD3 vs warm-up only (TD3) |"))
    cells = [c.strip() for c in row.split("|")[1:-1]]
    assert (cells[3], cells[4]) == ("451", "46.0")  # mean of 301 and 601; of 31 and 61 (3 figures)
    assert cells[5] == f"{mean['mapex_td3'] / mean['warmup_only_td3']:,.1f}x"
    assert "core-s (first)" in verdicts_part and cells[1] in ("beat", "lost to", "tied with")
    # the cost table: per method, and the specialists on their own line
    cost_part = text.split("## What each front cost", 1)[1].split("## ", 1)[0]
    mapex_row = next(line for line in cost_part.splitlines() if line.startswith("| MAPEX-TD3 |"))
    assert "| 451 ± 150 |" in mapex_row  # SEM of 301 and 601: 150
    spec_row = next(line for line in cost_part.splitlines() if line.startswith("| TD3 specialists"))
    assert "3,000 ± 0" in spec_row  # 3000 and 3001: mean 3000.5 ± 0.5, to whole seconds at that size
    # the figure: a file, captioned, whose curve for each run ends at its total
    assert (tmp_path / "report" / "cost.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "](cost.png)" in text
    loaded = [r for r in load_runs(root / "score", root / "evaluate", root / "provenance")]
    for r in loaded:
        x, y = cost_curve(r)
        assert x[-1] == pytest.approx(method_core_seconds(r)) and y[-1] == r.history["hypervolume"][-1]
        assert np.all(np.diff(x) > 0)
    fig = cost_figure(loaded, ENV_ID, 8.0)
    drawn = {line.get_label() for line in fig.axes[0].get_lines()}
    assert any("MAPEX-TD3" in d for d in drawn) and any("warm-up only" in d for d in drawn)
    assert fig.axes[0].get_xscale() == "log"


def test_cost_figure_averages_only_where_every_seed_has_a_record(monkeypatch):
    """A seed whose curve starts later (a seeded hybrid's first row, say) does not make the mean
    step down when it joins: the mean curve starts at the latest first record and is the mean of
    all seeds from there on."""
    from types import SimpleNamespace

    import pipeline.reporting.cost as cost_mod
    from pipeline.reporting.figures import cost_figure

    curves = {
        0: (np.array([1.0, 10.0, 100.0]), np.array([1.0, 2.0, 3.0])),
        1: (np.array([50.0, 200.0]), np.array([10.0, 11.0])),
    }
    monkeypatch.setattr(cost_mod, "cost_curve", lambda r: curves[r.seed])
    runs = [SimpleNamespace(method="mapex_td3", seed=s) for s in (0, 1)]
    fig = cost_figure(runs, ENV_ID, 8.0)
    (line,) = [ln for ln in fig.axes[0].get_lines() if "(mean of 2 seeds)" in ln.get_label()]
    x, y = np.asarray(line.get_xdata()), np.asarray(line.get_ydata())
    assert x.min() == 50.0
    # at 50 and 100 the mean of seed 0's step value (2, then 3) and seed 1's (10): never below its start
    assert list(zip(x, y)) == [(50.0, 6.0), (100.0, 6.5), (200.0, 7.0)]


def test_cost_table_shows_an_early_stop_and_the_fallbacks_only_where_a_run_has_them():
    from pipeline.reporting.cost import cost_table

    plain = [_run("mapex_td3", s, 1.0) for s in SEEDS]
    assert cost_table(plain, {}) == ""  # nothing recorded: no table
    runs = [_run("mapex_td3", s, 1.0) for s in SEEDS]
    for r, stop in zip(runs, (5, None)):
        r.origin = np.array(["specialist", "specialist", "child", "child", "child"])
        r.metrics |= {"stopped_at": stop, "init_fallbacks": {"a parent has hidden sizes [64, 64]": 1}}
    table = cost_table(runs, {("td3", 0): 12.0})
    header, _, row, spec = table.splitlines()
    assert "stopped early after iteration" in header and "children that fell back to warm-up" in header
    assert "of which interpolated seeds" not in header  # no run seeded
    assert "| 5, not stopped |" in row and "| 2 of 6 |" in row
    assert spec.startswith("| TD3 specialists") and "| 12.0 |" in spec


def test_training_frames_counts_each_specialist_and_a_shared_prefix_once():
    from pipeline.core.specialist import training_frames

    td3 = {"params": {"train_specialist": {"total_steps": 1000}, "td3": {}}}
    forked = {"params": {"train_specialist": {"total_steps": 1000}, "td3": {"shared_prefix_steps": 400}}}
    assert training_frames([td3, td3]) == 2000
    assert training_frames([forked, forked]) == 400 + 2 * 600  # the prefix once, then each its own
    assert training_frames([{"env_frames": 700}, {"env_frames": 800}]) == 1500  # PDERL
    assert training_frames([td3, {"source": {"imported": {"file": "x.zip"}}}]) is None  # trained elsewhere


def test_total_frames_figure_shifts_each_curve_by_its_specialists_frames():
    from pipeline.reporting.figures import total_frames_figure

    def run(method: str, seed: int, specialists: int | None) -> Run:
        r = _run(method, seed, 3.0)
        r.history = {"env_samples": np.array([0.0, 100.0]), "hypervolume": np.array([1.0, 3.0])}
        if specialists is not None:
            r.metrics["env_samples_specialists"] = specialists
        return r

    runs = [run("mapex_td3", s, 5000) for s in (0, 1)] + [run("morld", 0, 0), run("warmup_only_td3", 0, None)]
    fig = total_frames_figure(runs, ENV_ID, 8.0)
    lines = {ln.get_label(): np.asarray(ln.get_xdata()) for ln in fig.axes[0].get_lines()}
    mapex = next(x for name, x in lines.items() if name.startswith("MAPEX-TD3"))
    morld = next(x for name, x in lines.items() if name.startswith("MORL/D"))
    assert list(mapex) == [5000.0, 5100.0] and list(morld) == [0.0, 100.0]
    assert not any(name.startswith("warm-up") for name in lines), "a method without its specialists' frames is drawn"
    assert total_frames_figure([run("warmup_only_td3", 0, None)], ENV_ID, 8.0) is None
