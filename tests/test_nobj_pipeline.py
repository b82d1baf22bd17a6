"""Three objectives end to end: the whole DVC pipeline on a tiny mo-hopper-v5 preset (x velocity,
jump height, energy efficiency), in a temporary git + DVC copy of the repository.

The chain covers what the N-objective issue asks downstream of gap identification: TD3
specialists with N - 1 = 2 secondary critics each, MAPEX and the warm-up-only ablation with
3-parent facets and 3-component target weights, and one evaluator, score and report in 3-D.
Post-hoc critics and the baselines (PDERL specialists, MOPDERL, MORL/D) run on 3 objectives as
stage commands in this process (`cli`), which spares the chain a dozen stage start-ups.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from support.dvc_repo import DVC, make_repo, ran, run
from support.tiny_params import MOPDERL_TINY, MORLD_TINY, PDERL_TINY, with_lists
from support.tiny_params import TINY_CHAIN as TINY

# The whole DVC pipeline on three objectives: `make test-fast` leaves this file out.
pytestmark = pytest.mark.integration

HOPPER_REF = [-100.0, -3390.0, -1510.0]  # presets/envs.yaml


def tiny_hopper(methods: list[str]) -> dict:
    params = copy.deepcopy(TINY)
    params["env"] = {
        "id": "mo-hopper-v5",
        "max_episode_steps": 40,
        "reference_point": HOPPER_REF,
        "objective_names": None,
    }
    params["objectives"] = [0, 1, 2]
    params["methods"] = methods
    params["td3"] = {**TINY["td3"], "buffer_size": 2000}
    params["train_pderl"] = PDERL_TINY
    params["mopderl"] = MOPDERL_TINY
    params["morld"] = {**MORLD_TINY, "pop_size": 3}  # uniform weights need one agent per objective at least
    params["extract"] = {**TINY["extract"], "iterations": 3}
    params["evaluate"] = {"episodes": 1}
    for key in ("td3_seeds", "pderl_seeds", "fidelity_from", "posthoc_from", "method_runs"):
        params.pop(key, None)
    return with_lists(params)


@pytest.fixture(scope="module")
def hopper3(tmp_path_factory) -> Path:
    methods = ["mapex_td3", "warmup_only_td3"]
    root = make_repo(tmp_path_factory.mktemp("hopper3"), tiny_hopper(methods))
    out = run([DVC, "repro"], root)
    assert ran(out) == {
        "train_specialist",
        "critic_fidelity",
        "mapex_td3",
        "warmup_only_td3",
        "evaluate",
        "score",
        "render",
        "report",
    }
    return root


@pytest.mark.slow  # the 3-objective chain fixture (about a minute): slow keeps `make test` within 8 min
def test_specialists_carry_a_critic_for_every_objective(hopper3, tmp_path, cli):
    """Specialist k's joint critics (primary + N - 1 = 2 secondary) and the post-hoc ones fitted
    on its buffer (stage fit_critics, run here in this process): one critic per objective each."""
    from pipeline.core.checkpoint import load_critics

    for k in range(3):
        slot = hopper3 / "data" / "specialists" / "td3" / "seed0" / f"obj{k}"
        _, _, meta = load_critics(slot / "critics.pt")
        assert meta["objectives"] == [0, 1, 2] and meta["source"] == "joint", (k, meta)
        out = tmp_path / f"obj{k}"
        r = cli(
            "fit-critics", "--seed", 0, "--objective", k, "--specialist", slot, "--out", out,
            "--params", hopper3 / "params.yaml",
        )  # fmt: skip
        assert r.exit_code == 0, r.output
        _, _, meta = load_critics(out / "critics.pt")
        assert meta["objectives"] == [0, 1, 2] and meta["source"] == "posthoc", (k, meta)


@pytest.mark.slow  # the 3-objective chain fixture (about a minute): slow keeps `make test` within 8 min
def test_children_have_three_parents_and_three_weights(hopper3):
    from pipeline.core.population import load_population

    for method in ("mapex_td3", "warmup_only_td3"):
        members, meta = load_population(hopper3 / "data" / "fronts" / method / "seed0" / "population.pt")
        assert meta["n_objectives"] == 3
        assert meta["params"]["extract"]["facet_bridge_ratio"] == 3.0  # read with 3 objectives: recorded
        starts = [m for m in members if m.iteration == 0]
        children = [m for m in members if m.iteration >= 1]
        assert len(starts) == 3 and len(children) == 3, method
        for child in children:
            assert len(child.returns) == 3
            assert len(child.target_weight) == 3
            assert np.linalg.norm(child.target_weight) == pytest.approx(1.0)
            assert 1 <= len(child.parents) <= 3  # a facet's vertices, or fewer on a degenerate front


@pytest.mark.slow  # the 3-objective chain fixture (about a minute): slow keeps `make test` within 8 min
def test_every_method_is_scored_in_three_dimensions(hopper3):
    methods = yaml.safe_load((hopper3 / "params.yaml").read_text())["methods"]
    for method in methods:
        metrics = json.loads((hopper3 / "data" / "score" / method / "seed0" / "metrics.json").read_text())
        assert metrics["method"] == method
        front = metrics["front"]
        assert front["cardinality"] >= 1 and front["hypervolume"] >= 0.0
        assert np.isfinite(front["sparsity"]) and np.isfinite(front["expected_utility"])
    report = (hopper3 / "data" / "report" / "report.md").read_text()
    assert "With 3 objectives" in report
    for name in ("| MAPEX-TD3 |", "| warm-up only (TD3) |", "| TD3 specialists only |", "energy efficiency"):
        assert name in report, name
    assert list((hopper3 / "data" / "report").glob("front_seed0.*"))
    # a second repro runs nothing: the 3-objective stages are as pure as the 2-objective ones
    assert ran(run([DVC, "repro"], hopper3)) == set()


def test_morld_needs_an_agent_per_objective(tmp_path, cli):
    """Uniform MORL/D weights on 3 objectives with 2 agents: one line naming the key and the
    env, exit 2, before anything is trained (pymoo would fail deep inside otherwise)."""
    pytest.importorskip("morl_baselines")
    params = tiny_hopper(["morld"])
    params["morld"] = {**MORLD_TINY, "pop_size": 2}
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(params))
    out = tmp_path / "out"
    r = cli("morld", "--seed", 0, "--out", out, "--params", path)
    assert r.exit_code == 2, r.output
    assert "morld.pop_size = 2" in r.output and "mo-hopper-v5" in r.output and "3 objectives" in r.output
    assert not (out / "population.pt").exists()


def test_baselines_on_three_objectives(tmp_path, cli):
    """PDERL specialists for 3 objectives, then MOPDERL's phase 2 from them (NSGA-II ranks and
    crowding over 3 objectives, one RL agent per objective) and MORL/D (when its extra is
    installed) on mo-hopper-v5 at a tiny budget: every member has 3 returns, MOPDERL starts
    from all three populations and adds individuals, MORL/D's weights span 3 objectives."""
    from pipeline.core.population import load_population

    params = tiny_hopper(["mopderl", "morld"])
    params["morld"] = {**MORLD_TINY, "pop_size": 3}
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(params))
    pderl = tmp_path / "pderl"
    r = cli("train-pderl", "--seed", 0, "--out", pderl, "--params", path)
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in pderl.iterdir()) == ["obj0", "obj1", "obj2"]

    out = tmp_path / "mopderl"
    r = cli(
        "mopderl",
        "--seed",
        0,
        "--specialists",
        pderl,
        "--out",
        out,
        "--params",
        path,
        "--resume-dir",
        tmp_path / "resume",
    )
    assert r.exit_code == 0, r.output
    members, meta = load_population(out / "population.pt")
    assert meta["n_objectives"] == 3 and all(len(m.returns) == 3 for m in members)
    starts = [m for m in members if m.origin == "specialist"]
    assert sorted({m.objective for m in starts}) == [0, 1, 2]
    assert any(m.origin == "mopderl" for m in members)

    pytest.importorskip("morl_baselines")
    out = tmp_path / "morld"
    r = cli("morld", "--seed", 0, "--out", out, "--params", path)
    assert r.exit_code == 0, r.output
    members, meta = load_population(out / "population.pt")
    assert meta["n_objectives"] == 3 and members
    for m in members:
        assert len(m.returns) == 3 and len(m.target_weight) == 3
        assert sum(m.target_weight) == pytest.approx(1.0)
    # the uniform weights of 3 agents on 3 objectives: the simplex's corners
    assert {tuple(np.round(m.target_weight, 6)) for m in members} <= {(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)}
