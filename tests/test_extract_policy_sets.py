"""Extraction from many starting policies per specialist (policy sets, policies.pt) through the
real `mapex` commands: the initial population is every policy of every set, each evaluated;
children are made over the whole population; evaluate, score and report show the starting
policies apart from the children. A set of one is exactly the TD3 single-policy path.
(The policy-set file itself: tests/test_policyset.py.)"""

from __future__ import annotations

import csv
import json
import shutil
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.core.checkpoint import actor_from_meta, load_policy
from pipeline.core.envs import make_env
from pipeline.core.pareto import pareto_mask
from pipeline.core.policyset import load_policy_set, save_policy_set
from pipeline.core.population import load_population
from pipeline.evaluation.episodes import eval_seeds, evaluate_policy

# Specialists, then extract/evaluate/score/report in subprocesses: `make test-fast` leaves this file out.
pytestmark = pytest.mark.integration

EXTRACT = {
    "iterations": 2,
    "child_buffer_size": 200,
    "eval_episodes": 1,
    "warmup_steps": 10,
    "warmup_batch_size": 32,
    "epochs": 1,
    "beta": 1.0,
    "omega_max": 1.0,
    "batch_size": 32,
    "hidden_sizes": [16, 16],
    "device": "cpu",
}
NAMES = ["rl", "pop0", "pop1"]  # the RL actor (policy.pt's) and two population actors
CAP = 100  # the tiny preset's env.max_episode_steps (HalfCheetah: every episode runs to it)


@pytest.fixture(scope="module")
def trained(tmp_path_factory, write_params, mapex) -> Path:
    """TD3 specialists of seed 0 (both objectives), trained once for this module."""
    root = tmp_path_factory.mktemp("sets")
    params = write_params(root, {"extract": EXTRACT})
    r = mapex("train-specialist", "--seed", "0", "--out", root / "specs", "--params", params, cwd=root)
    assert r.returncode == 0, r.stderr
    return root / "specs"


def write_set(slot: Path, names: list[str] = NAMES, **meta_changes) -> None:
    """slot/policies.pt: the slot's policy.pt actor as "rl" and fresh actors of its architecture
    for the other names (seeded by slot and position), meta = policy.pt's (plus changes)."""
    rl, meta = load_policy(slot / "policy.pt")
    actors = []
    for i, name in enumerate(names):
        if name == "rl":
            actors.append(rl)
            continue
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(1000 * meta["objective"] + i)
            actors.append(actor_from_meta(meta))
    save_policy_set(slot / "policies.pt", actors, names, [None] * len(names), {**meta, **meta_changes})


@pytest.fixture
def specs(trained, tmp_path) -> Path:
    """A private copy of the specialists with a policy set of 3 in each slot."""
    root = Path(shutil.copytree(trained, tmp_path / "specs"))
    for k in (0, 1):
        write_set(root / f"obj{k}")
    return root


def extract(mapex, write_params, tmp_path: Path, specs: Path, name: str = "out", out: Path | None = None, **updates):
    params = write_params(tmp_path, {"extract": {**EXTRACT, **updates}}, name=f"{name}.yaml")
    return mapex(
        "extract",
        "--seed",
        0,
        "--specialists",
        specs,
        "--out",
        out or tmp_path / name,
        "--resume-dir",
        tmp_path / f"resume_{name}",
        "--params",
        params,
        cwd=tmp_path,
    )


def assert_refused(r, tmp_path: Path, *fragments: str, name: str = "out") -> None:
    """Exit 2, one `error:` line holding every fragment, no output written."""
    assert r.returncode == 2, r.stderr
    lines = [line for line in r.stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1, r.stderr
    for f in fragments:
        assert f in lines[0], (f, lines[0])
    assert not (tmp_path / name).exists()


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


# ---------------------------------------------------------------- extraction from policy sets


def test_initial_population_is_every_policy_of_every_set(specs, tmp_path, mapex, write_params):
    r = extract(mapex, write_params, tmp_path, specs)
    assert r.returncode == 0, r.stderr
    members, meta = load_population(tmp_path / "out" / "population.pt")
    start, children = members[:6], members[6:]
    assert [(m.origin, m.objective, m.policy_name, m.iteration) for m in start] == [
        ("specialist", k, name, 0) for k in (0, 1) for name in NAMES
    ]
    assert [m.origin for m in children] == ["child", "child"] and [m.iteration for m in children] == [1, 2]
    assert all(m.policy_name is None and m.objective is None for m in children)
    # each starting policy evaluated (one episode of CAP steps each, cumulative), with its own weights
    assert [m.env_samples for m in members] == [CAP * (i + 1) for i in range(8)]
    assert all(len(m.returns) == 2 and m.eval_episodes == 1 and m.parents == [] for m in start)
    for k in (0, 1):
        pset = load_policy_set(specs / f"obj{k}" / "policies.pt")
        for m, actor in zip(start[3 * k : 3 * k + 3], pset.actors):
            assert all(torch.equal(m.actor[n], v) for n, v in actor.state_dict().items())
            assert m.hidden_sizes == list(pset.meta["hidden_sizes"])
    # member i is evaluated on extraction stream i, whichever set it came from
    envs = [make_env("mo-halfcheetah-v5", CAP)]
    pset = load_policy_set(specs / "obj1" / "policies.pt")
    assert evaluate_policy(pset.actors[1], envs, eval_seeds(0, 0, 4, 1)).mean.tolist() == start[4].returns
    # parents are chosen over the whole population: non-dominated among the members before the child
    for i, child in enumerate(children, start=6):
        on_front = pareto_mask(np.array([m.returns for m in members[:i]]))
        assert len(child.parents) == 2 and all(on_front[p] for p in child.parents), (i, child.parents)
    lines = (tmp_path / "out" / "history.csv").read_text().splitlines()
    assert [line.split(",")[1] for line in lines[1:]] == ["6", "7", "8"]
    assert lines[1].split(",")[3] == str(6 * CAP)
    assert not (tmp_path / "resume_out" / "extract" / "mapex_td3" / "seed0").exists()  # progress removed when done

    # evaluate, score and report: every starting policy re-evaluated and shown apart from the children
    params = write_params(
        tmp_path,
        {
            "env": {"reference_point": [-100.0, -4500.0]},
            "evaluate": {"episodes": 1},
            "report": {"dpi": 50, "formats": ["png"]},
        },
        name="post.yaml",
    )
    ev, sc = tmp_path / "evaluate" / "mapex_td3" / "seed0", tmp_path / "score" / "mapex_td3" / "seed0"
    r = mapex(
        "evaluate",
        "--population",
        tmp_path / "out" / "population.pt",
        "--out",
        ev,
        "--seed",
        0,
        "--params",
        params,
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stderr
    rows = read_csv(ev / "evaluated.csv")
    assert [(row["origin"], row["objective"], row["policy_name"]) for row in rows] == [
        *(("specialist", str(k), name) for k in (0, 1) for name in NAMES),
        ("child", "", ""),
        ("child", "", ""),
    ]
    assert json.loads((ev / "evaluation.json").read_text())["env_samples_evaluation"] == 8 * CAP
    r = mapex(
        "score",
        "--population",
        tmp_path / "out" / "population.pt",
        "--evaluated",
        ev,
        "--out",
        sc,
        "--params",
        params,
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stderr
    metrics = json.loads((sc / "metrics.json").read_text())
    assert (metrics["population"], metrics["starting_policies"], metrics["children"]) == (8, 6, 2)
    r = mapex(
        "report",
        "--evaluated",
        tmp_path / "evaluate",
        "--scored",
        tmp_path / "score",
        "--out",
        tmp_path / "report",
        "--params",
        params,
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stderr
    text = (tmp_path / "report" / "report.md").read_text()
    assert "- starting policies per specialist: specialist 0: 3, specialist 1: 3" in text
    table = [line for line in text.splitlines() if line.startswith("| Method")][0].split("|")
    mapex_row = [line for line in text.splitlines() if line.startswith("| MAPEX-TD3 |")][0].split("|")
    spec_row = [line for line in text.splitlines() if line.startswith("| TD3 specialists only |")][0].split("|")
    col = [c.strip() for c in table].index("starting policies")
    assert (mapex_row[col].strip(), mapex_row[col + 1].strip()) == ("6", "2")
    assert (spec_row[col].strip(), spec_row[col + 1].strip()) == ("6", "0")
    assert (tmp_path / "report" / "front_seed0.png").stat().st_size > 5000


def test_a_set_of_one_is_the_td3_path(trained, tmp_path, mapex, write_params):
    """policies.pt holding only the RL actor gives bit for bit the population policy.pt gives
    (the policy name aside), and the TD3 path evaluates specialist k on stream k as before."""
    td3 = extract(mapex, write_params, tmp_path, trained, name="td3")
    assert td3.returncode == 0, td3.stderr
    one = Path(shutil.copytree(trained, tmp_path / "one"))
    for k in (0, 1):
        write_set(one / f"obj{k}", names=["rl"])
    r = extract(mapex, write_params, tmp_path, one, name="set")
    assert r.returncode == 0, r.stderr
    a, meta_a = load_population(tmp_path / "td3" / "population.pt")
    b, meta_b = load_population(tmp_path / "set" / "population.pt")
    assert [m.policy_name for m in a] == ["policy", "policy", None, None]
    assert [m.policy_name for m in b] == ["rl", "rl", None, None]
    for x, y in zip(a, b):
        assert {**asdict(x), "actor": None, "policy_name": None} == {**asdict(y), "actor": None, "policy_name": None}
        assert all(torch.equal(x.actor[n], y.actor[n]) for n in x.actor)
    assert (tmp_path / "td3" / "history.csv").read_text() == (tmp_path / "set" / "history.csv").read_text()
    envs = [make_env("mo-halfcheetah-v5", CAP)]
    for k in (0, 1):
        actor, _ = load_policy(trained / f"obj{k}" / "policy.pt")
        assert evaluate_policy(actor, envs, eval_seeds(0, 0, k, 1)).mean.tolist() == a[k].returns


def test_resume_with_policy_sets(trained, specs, tmp_path, mapex, write_params):
    """Progress of a run from policy sets resumes (6 starting members, then whole iterations);
    progress made from policy.pt alone is not resumed once a policies.pt appears."""
    blocked = tmp_path / "blocked"
    blocked.write_text("")  # OUT is a plain file: the run fails writing its outputs, after its last checkpoint
    r = extract(mapex, write_params, tmp_path, specs, name="sets", out=blocked, children_per_iteration=2)
    assert r.returncode != 0
    progress = tmp_path / "resume_sets" / "extract" / "mapex_td3" / "seed0"
    assert torch.load(progress / "state.pt", weights_only=True)["n_items"] == 6 + 2 * 2
    item = torch.load(progress / "state.item_00006.pt", weights_only=True)  # the first child
    item["item"]["returns_std"] = [-1.0, -1.0]  # steers nothing: tells a resumed run from a fresh one
    torch.save(item, progress / "state.item_00006.pt")
    r = extract(mapex, write_params, tmp_path, specs, name="sets", children_per_iteration=2)
    assert r.returncode == 0, r.stderr
    members, _ = load_population(tmp_path / "sets" / "population.pt")
    assert len(members) == 10 and members[6].returns_std == [-1.0, -1.0]
    assert [m.iteration for m in members] == [0] * 6 + [1, 1, 2, 2]

    # progress from the TD3 specialists, then policy sets added: the run starts over
    td3 = Path(shutil.copytree(trained, tmp_path / "td3specs"))
    r = extract(mapex, write_params, tmp_path, td3, name="grow", out=blocked)
    assert r.returncode != 0
    assert (
        torch.load(tmp_path / "resume_grow" / "extract" / "mapex_td3" / "seed0" / "state.pt", weights_only=True)[
            "n_items"
        ]
        == 4
    )
    for k in (0, 1):
        write_set(td3 / f"obj{k}")
    r = extract(mapex, write_params, tmp_path, td3, name="grow")
    assert r.returncode == 0, r.stderr
    members, _ = load_population(tmp_path / "grow" / "population.pt")
    assert [m.origin for m in members] == ["specialist"] * 6 + ["child"] * 2


@pytest.mark.parametrize(
    "change, fragments",
    [
        ({"objective": 1}, ["obj0/policies.pt (objective = 1)", "obj0/buffer.zarr (objective = 0)"]),
        (
            {"env_id": "mo-hopper-v5"},
            ["obj0/policies.pt (env_id = 'mo-hopper-v5')", "obj0/buffer.zarr (env_id = 'mo-halfcheetah-v5')"],
        ),
        ({"seed": 7}, ["obj0/policies.pt (seed = 7)", "obj0/buffer.zarr (seed = 0)"]),
        ({"obs_dim": 5}, ["obj0/policies.pt (obs_dim = 5)", "obj0/buffer.zarr (obs_dim = 17)"]),
    ],
)
def test_a_set_of_another_specialist_is_refused(specs, tmp_path, mapex, write_params, change, fragments):
    if "obs_dim" in change:  # weights that fit the changed dims, so the cross-check is what refuses it
        _, meta = load_policy(specs / "obj0" / "policy.pt")
        meta = {**meta, **change}
        save_policy_set(specs / "obj0" / "policies.pt", [actor_from_meta(meta)], ["rl"], [None], meta)
    else:
        write_set(specs / "obj0", **change)
    r = extract(mapex, write_params, tmp_path, specs)
    assert_refused(r, tmp_path, *fragments)


def test_a_broken_set_is_refused_not_replaced_by_policy_pt(specs, tmp_path, mapex, write_params):
    (specs / "obj1" / "policies.pt").write_bytes(b"not a torch file")
    r = extract(mapex, write_params, tmp_path, specs)
    assert_refused(r, tmp_path, "obj1/policies.pt", "cannot be read")
