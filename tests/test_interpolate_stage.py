"""The interpolation baseline through DVC: `dvc repro` of its score stage on a tiny preset (TD3
specialists, interpolation, evaluation, scoring), its front read by score like any method's."""

from __future__ import annotations

import json

import pytest
from support.dvc_repo import DVC, make_repo, ran, run
from support.tiny_params import TINY_CHAIN, with_lists

from pipeline.core.population import load_population

# Runs the DVC pipeline in subprocesses: `make test-fast` leaves this file out; and slow, so
# `make test` stays within 8 minutes (the every-method chain in test_dvc_methods.py, also slow,
# runs interpolation too; tests/test_interpolate.py covers the stage's pieces in the fast tier).
pytestmark = [pytest.mark.integration, pytest.mark.slow]


def test_dvc_repro_scores_the_interpolation_front(tmp_path):
    params = with_lists({**TINY_CHAIN, "methods": ["mapex_td3", "interpolate_td3"]})
    params["extract"] = {**params["extract"], "children_per_iteration": 2}
    repo = make_repo(tmp_path / "repo", params)
    # its own chain only (the report's verdict pair is checked in tests/test_interpolate.py)
    out = run([DVC, "repro", "score@0-interpolate_td3"], repo)
    assert ran(out) == {"train_specialist", "interpolate_td3", "evaluate", "score"}

    k = params["extract"]["iterations"] * 2  # MAPEX's children: iterations x children_per_iteration
    members, meta = load_population(repo / "data/fronts/interpolate_td3/seed0/population.pt")
    assert meta["method"] == "interpolate_td3" and len(members) == 2 + k
    assert [m.iteration for m in members] == [0, 0] + [1 + j // 2 for j in range(k)]
    metrics = json.loads((repo / "data/score/interpolate_td3/seed0/metrics.json").read_text())
    assert metrics["method"] == "interpolate_td3" and metrics["children"] == k and metrics["starting_policies"] == 2
    # its only env frames: its evaluations, (2 + k) policies x eval_episodes x 40 steps (no termination)
    episodes, steps = params["extract"]["eval_episodes"], params["env"]["max_episode_steps"]
    assert metrics["env_samples_extraction"] == (2 + k) * episodes * steps
    assert metrics["env_samples_collection"] == 0
    front = (repo / "data/score/interpolate_td3/seed0/front.csv").read_text().splitlines()
    assert front[0].startswith("id,origin,iteration") and len(front) > 1
    curve = (repo / "data/score/interpolate_td3/seed0/hypervolume.csv").read_text().splitlines()
    assert len(curve) == 1 + 1 + params["extract"]["iterations"]  # header, the start, each iteration
    # changing an advantage-weighted key of extract leaves it up to date; the children's count reruns it
    (repo / "params.yaml").write_text((repo / "params.yaml").read_text().replace("beta: 1.0", "beta: 0.5"))
    assert "changed" not in run([DVC, "status", "interpolate_td3"], repo)
    (repo / "params.yaml").write_text((repo / "params.yaml").read_text().replace("iterations: 2", "iterations: 3"))
    assert "extract.iterations" in run([DVC, "status", "interpolate_td3"], repo)
