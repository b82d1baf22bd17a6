"""benchmarks/jobqueue.py, benchmarks/answer_summary.py and benchmarks/answer.sh (docs/results.md
section 10): the queue runs each job once its inputs exist, best first, and never twice; the summary
pairs methods by seed with the report's rule; the whole design runs and reports on a tiny preset."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from support.tiny_params import TINY_CHAIN, merge, with_lists

ROOT = Path(__file__).resolve().parents[1]


def run_design(script: str, params: dict, tmp_path: Path, slots: int, timeout: int, **env: str):
    """Run benchmarks/SCRIPT on PARAMS (written to tmp_path) into tmp_path/w with extra env
    variables; returns the finished process and the work folder."""
    p = tmp_path / "params.yaml"
    p.write_text(yaml.safe_dump(params))
    work = tmp_path / "w"
    full = {**os.environ, "PYTHON": sys.executable, "PYTHONPATH": str(ROOT), **env}
    r = subprocess.run(
        ["bash", f"benchmarks/{script}", str(work), str(p), str(slots)],
        cwd=ROOT,
        env=full,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    return r, work


def run_script(script: str, *args: Path) -> subprocess.CompletedProcess:
    """python benchmarks/SCRIPT ARGS..., with the repository importable; the finished process."""
    return subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / script), *map(str, args)],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )


def run_queue(plan: Path, log: Path, slots: int = 2) -> subprocess.CompletedProcess:
    return subprocess.run(
        [
            sys.executable,
            str(ROOT / "benchmarks/jobqueue.py"),
            str(plan),
            "--slots",
            str(slots),
            "--log",
            str(log),
            "--poll",
            "0.1",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=plan.parent,
    )


def test_queue_runs_jobs_after_their_inputs_and_skips_what_is_done(tmp_path):
    order = tmp_path / "order.txt"
    rows = [  # NAME DONE DEPS COMMAND; 'b' is listed first but needs a's output
        ("b", "b.out", "a.out", f"echo b >> {order} && touch b.out"),
        ("a", "a.out", "-", f"sleep 0.5 && echo a >> {order} && touch a.out"),
        ("done_before", "old.out", "-", f"echo again >> {order}"),
        ("fails", "f.out", "-", f"echo f >> {order}; exit 3"),
        ("after_fail", "g.out", "f.out", f"echo g >> {order} && touch g.out"),
    ]
    (tmp_path / "old.out").write_text("")
    plan = tmp_path / "plan.tsv"
    plan.write_text("# a comment\n" + "".join("\t".join(r) + "\n" for r in rows))
    r = run_queue(plan, tmp_path / "logs", slots=1)
    assert r.returncode == 0, r.stderr
    # one slot: a runs before b (b waited for a.out); the done job never runs; the failed one once
    assert order.read_text().split() == ["a", "b", "f"]
    assert "fails: FAILED (exit 3)" in r.stdout
    assert "never started (inputs missing): ['after_fail']" in r.stdout


def test_queue_names_a_malformed_plan_line(tmp_path):
    plan = tmp_path / "plan.tsv"
    plan.write_text("only\ttwo\n")
    r = run_queue(plan, tmp_path / "logs")
    assert r.returncode != 0 and "plan.tsv:1: expected 4 tab-separated fields" in r.stderr


def metrics(hv: float, eu: float = 1.0, distinct: int = 3, spec: float = 10.0) -> dict:
    return {
        "env_id": "mo-halfcheetah-v5",
        "reference_point": [-100.0, -4500.0],
        "episodes": 10,
        "children": 48,
        "front": {"hypervolume": hv, "expected_utility": eu, "distinct_count": distinct},
        "specialists": {"hypervolume": spec, "expected_utility": 0.5, "distinct_count": 1},
    }


def test_summary_pairs_methods_by_seed_with_the_reports_rule(tmp_path):
    hv = {  # per label, per seed: paper beats warm-up in every seed; gentle is a coin toss
        "paper_mapex": [30.0, 32.0, 28.0],
        "warmup": [20.0, 21.0, 19.0],
        "gentle_mapex": [25.0, 15.0, 21.0],
        "interp": [20.0, 22.0, 18.0],
    }
    for label, values in hv.items():
        for seed, v in enumerate(values):
            f = tmp_path / "score" / label / f"seed{seed}" / "metrics.json"
            f.parent.mkdir(parents=True)
            f.write_text(json.dumps(metrics(v)))
    # the forms' rows are named with the values in answer.sh's params files (here Hopper's paper values)
    (tmp_path / "paper.yaml").write_text("extract: {epochs: 10, lr: 0.0003, beta: 0.1, omega_max: 20.0}\n")
    (tmp_path / "gentle.yaml").write_text("extract: {epochs: 1, lr: 0.0001, beta: 0.1, omega_max: 20.0}\n")
    out = run_script("answer_summary.py", tmp_path)
    assert out.returncode == 0, out.stderr
    rows = {line.split("|")[1].strip(): line for line in out.stdout.splitlines() if line.startswith("| ")}
    paper = rows["MAPEX, paper form (10 epochs, lr 0.0003, beta 0.1, omega_max 20)"]
    # paper - warm-up = (10, 11, 9): mean 10 (+50% of 20), SEM 0.577: 17.3 SEM
    assert "**beat**: +50.0%, 17.3 SEM, higher in 3/3" in paper
    assert "30 ± 1.15" in paper  # mean ± SEM of 30, 32, 28
    gentle = rows["MAPEX, gentle form (1 epoch, lr 0.0001, beta 0.1, omega_max 20)"]
    assert "tied: +1.7%" in gentle and "higher in 2/3" in gentle
    # specialists alone: their own front's scores (here one specialist dominates: 1 distinct point)
    assert [c.strip() for c in rows["specialists alone"].split("|")[3:7]] == ["10 ± 0", "0.5 ± 0", "1 ± 0", "0"]
    assert rows["0"].split("|")[2].strip() == "10 (1)"
    # no shared-init run: neither its row nor the footnote about it
    assert "shared-init" not in out.stdout

    f = tmp_path / "score" / "interp_shared" / "seed0" / "metrics.json"
    f.parent.mkdir(parents=True)
    f.write_text(json.dumps(metrics(26.0, spec=12.0)))
    out = run_script("answer_summary.py", tmp_path)
    assert out.returncode == 0, out.stderr
    rows = {line.split("|")[1].strip(): line for line in out.stdout.splitlines() if line.startswith("| ")}
    # one seed: the value alone, no ± (cells: seeds, hypervolume)
    assert [c.strip() for c in rows["interpolation, shared-init specialists"].split("|")[2:4]] == ["0", "26"]
    assert [c.strip() for c in rows["shared-init specialists alone"].split("|")[2:4]] == ["0", "12"]
    assert "The shared-init row pairs different specialists of the same seed." in out.stdout


def test_summary_without_scores_names_the_folder(tmp_path):
    out = run_script("answer_summary.py", tmp_path)
    assert out.returncode != 0 and f"{tmp_path}/score: no LABEL/seedS/metrics.json" in out.stderr


@pytest.mark.integration
@pytest.mark.slow  # every method of the design on two seeds: slow keeps `make test` within 8 minutes
def test_answer_design_runs_and_reports_on_a_tiny_preset(tmp_path):
    params = with_lists(
        merge(
            TINY_CHAIN,
            {
                "seeds": [0, 1],
                "methods": ["mapex_td3", "warmup_only_td3", "interpolate_td3"],
                "extract": {"epochs": 3},
            },
        )
    )
    r, work = run_design("answer.sh", params, tmp_path, 2, 900, SHARED_SEEDS="0")
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    queue = (work / "logs" / "queue.log").read_text()
    assert "failed: none" in queue, queue
    assert (yaml.safe_load((work / "shared.yaml").read_text())["td3"]["shared_init"]) is True
    for form in ("paper", "gentle"):
        report = (work / "report" / form / "report.md").read_text()
        assert "warm-up only" in report and "interpolation" in report.lower(), report[:2000]
    summary = (work / "summary.md").read_text()
    for name in ("MAPEX, paper form", "MAPEX, gentle form", "warm-up only", "interpolation, shared-init specialists"):
        assert f"| {name}" in summary, summary


def test_answer_seeds_override_rewrites_the_params_files_and_the_plan(tmp_path):
    # SEEDS adds seeds to a finished run (docs/results.md section 11): the three params files get the
    # new seeds with their generated run lists in step, and the plan covers exactly those seeds
    params = with_lists(merge(TINY_CHAIN, {"seeds": [0, 1], "methods": ["mapex_td3", "warmup_only_td3"]}))
    # SHARED_SEEDS unset: the shared-init seeds follow SEEDS
    r, work = run_design("answer.sh", params, tmp_path, 1, 300, SEEDS="3 5", PLAN_ONLY="1", SHARED_SEEDS="")
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    for form in ("paper", "gentle", "shared"):
        written = yaml.safe_load((work / f"{form}.yaml").read_text())
        generated = yaml.safe_load((work / f"{form}.gen.yaml").read_text())  # beside it, by sync-params
        assert written["seeds"] == [3, 5] and generated["td3_seeds"] == [3, 5], form
    names = [line.split("\t")[0] for line in (work / "plan.tsv").read_text().splitlines()]
    assert [n for n in names if n.startswith("spec_td3_")] == ["spec_td3_3", "spec_td3_5"]
    assert [n for n in names if n.startswith("spec_shared_")] == ["spec_shared_3", "spec_shared_5"]


def tiny_hopper3() -> dict:
    """TINY_CHAIN on the 3-objective mo-hopper-v5 (40-step episodes), MAPEX and warm-up only."""
    params = merge(
        TINY_CHAIN,
        {
            "env": {"id": "mo-hopper-v5", "max_episode_steps": 40, "reference_point": [-100.0, -3390.0, -1510.0]},
            "objectives": [0, 1, 2],
            "methods": ["mapex_td3", "warmup_only_td3"],
            "td3": {"buffer_size": 2000},
            "extract": {"iterations": 3, "facet_bridge_ratio": 3.0},
            "evaluate": {"episodes": 1},
        },
    )
    for key in ("td3_seeds", "extract_from", "extract_variants", "warmup_from", "interpolate_from"):
        params.pop(key, None)
    return with_lists(params)


def test_facets_refuses_two_objectives_naming_the_file(tmp_path):
    params = with_lists(merge(TINY_CHAIN, {"methods": ["mapex_td3"]}))
    r, _ = run_design("facets.sh", params, tmp_path, 1, 120, PLAN_ONLY="1")
    p = tmp_path / "params.yaml"
    assert r.returncode != 0 and f"{p}: objectives [0, 1]: the facet rule needs 3 or more objectives" in r.stderr


@pytest.mark.integration
@pytest.mark.slow  # three specialists and three extractions: slow keeps `make test` within 8 minutes
def test_facets_design_runs_before_and_after_on_a_tiny_3_objective_preset(tmp_path):
    r, work = run_design("facets.sh", tiny_hopper3(), tmp_path, 2, 900)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "failed: none" in (work / "logs" / "queue.log").read_text()
    assert yaml.safe_load((work / "before.yaml").read_text())["extract"]["facet_bridge_ratio"] is None
    assert yaml.safe_load((work / "after.yaml").read_text())["extract"]["facet_bridge_ratio"] == 3.0
    # one job per specialist: three objectives of seed 0, each with its own provenance record
    assert sorted(f.name for f in (work / "provenance" / "specialists" / "seed0").iterdir()) == [
        "obj0.json",
        "obj1.json",
        "obj2.json",
    ]
    for form in ("after", "before"):
        assert "warm-up only" in (work / "report" / form / "report.md").read_text()
    summary = (work / "summary.md").read_text()
    rows = {line.split("|")[1].strip(): line for line in summary.splitlines() if line.startswith("| ")}
    for name in ("MAPEX, facet rule (after)", "MAPEX, every facet (before)", "warm-up only", "specialists alone"):
        assert name in rows, summary
    assert (
        "tied" in rows["MAPEX, facet rule (after)"] or "–" in rows["MAPEX, facet rule (after)"]
    )  # one seed: no verdict
    seed0 = rows["0"].split("|")
    assert seed0[-3].count(":") == 3, seed0  # the three specialists' return vectors
    # the replay: one row per iteration of each seed, at the preset's ratio
    replay = (work / "replay.md").read_text()
    assert "facet_bridge_ratio 3.0" in replay
    assert sum(line.startswith("| 0 |") for line in replay.splitlines()) == tiny_hopper3()["extract"]["iterations"]


def test_facets_replay_tells_whether_the_rule_changed_a_draw(tmp_path):
    """A thin curved front (issue 31's arc) changes the gaps at ratio 3; a triangle of three of its
    points does not."""
    import numpy as np
    import torch

    t = np.linspace(0, np.pi / 2, 12)
    arc = np.stack([np.cos(t), np.sin(t), np.sin(2 * t)], axis=1)
    # iteration 0: the arc's two ends and a middle point; iteration 1: the rest of the arc
    start = [0, 6, 11]
    members = [{"iteration": 0, "returns": arc[i].tolist()} for i in start]
    members += [{"iteration": 1, "returns": arc[i].tolist()} for i in range(12) if i not in start]
    members += [{"iteration": 2, "returns": [0.0, 0.0, 0.0]}]
    f = tmp_path / "fronts" / "after" / "seed0" / "population.pt"
    f.parent.mkdir(parents=True)
    torch.save({"meta": {"n_objectives": 3}, "members": members}, f)
    r = run_script("facets_replay.py", tmp_path)
    assert r.returncode == 0, r.stderr
    rows = [line.split("|")[1:-1] for line in r.stdout.splitlines() if line.startswith("| 0 ")]
    rows = [[c.strip() for c in row] for row in rows]
    # iteration 1 draws from one triangle (unchanged by the rule); iteration 2 from the whole
    # arc, whose 10 facets the rule replaces by 3 facets and 7 steps (tests/test_gaps.py)
    assert rows[0][:7] == ["0", "1", "3", "3", "1", "1", "no"]
    assert rows[1][:7] == ["0", "2", "12", "12", "10", "10", "yes"]
    assert float(rows[1][7]) < 3.0


def test_facets_replay_refuses_two_objectives_naming_the_file(tmp_path):
    import torch

    f = tmp_path / "fronts" / "after" / "seed0" / "population.pt"
    f.parent.mkdir(parents=True)
    torch.save({"meta": {"n_objectives": 2}, "members": [{"iteration": 1, "returns": [0.0, 0.0]}]}, f)
    r = run_script("facets_replay.py", tmp_path)
    assert r.returncode != 0 and f"{f}: 2 objectives; the facet rule is for 3 or more" in r.stderr
