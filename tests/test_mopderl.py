"""MOPDERL phase 2 (pipeline/baselines/mopderl.py, its NSGA-II tools in pipeline/baselines/nsga2.py, stages/mopderl.py).

NSGA-II pieces on hand-checkable points; the tournament and critic rules; the frame and
update accounting of a generation and bitwise checkpoint resumption, on synthetic RL agents;
and the real stage end to end on tiny PDERL specialists (built by the real train_pderl stage),
killed mid-run and resumed to the same bits, and refusing specialists of another seed.
"""

from __future__ import annotations

import copy
import csv
import io
import os
import shutil
import signal
from pathlib import Path

import numpy as np
import pytest
import torch
import typer
from typer.testing import CliRunner

from pipeline.baselines.mopderl import (
    AgentInit,
    MopderlRun,
    StartingActor,
    crossover_critic,
)
from pipeline.baselines.nsga2 import (
    archive_update,
    crowding_distance,
    nondominated_ranks,
    nsga2_scores,
    nsga2_select,
    preference_positions,
    tournament_pair,
    tournament_winner,
)
from pipeline.core.envs import env_spec, make_env
from pipeline.core.nets import Actor, CriticEnsemble
from pipeline.core.pareto import pareto_mask
from pipeline.core.population import load_population
from pipeline.params.mopderl import MopderlParams
from pipeline.params.td3 import TD3Params
from stages.mopderl import mopderl as mopderl_stage
from stages.train_pderl import train_pderl as train_pderl_stage

CAP = 30
TD3 = {"learning_starts": 100, "buffer_size": 5000, "batch_size": 32, "hidden_sizes": [16]}
PDERL = {
    "total_frames": 200,
    "population_size": 3,
    "mini_buffer_size": 200,
    "crossover_transitions": 64,
    "crossover_batch_size": 32,
    "crossover_epochs": 2,
    "mutation_states": 32,
    "checkpoint_every": 1,
    "device": "cpu",
}
MOPDERL = {
    "total_frames": 1700,
    "population_size": 4,
    "children": 3,
    "eval_episodes": 1,
    "mini_buffer_size": 200,
    "crossover_transitions": 64,
    "crossover_batch_size": 32,
    "crossover_epochs": 2,
    "mutation_states": 32,
    "rl_updates_per_frame": 0.1,
    "device": "cpu",
}


@pytest.fixture(autouse=True, scope="module")
def one_torch_thread():
    """One torch thread, as `mapex` runs stages by default: tiny nets are slower on more, and
    far slower on a busy machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


# ----------------------------------------------------------------------------- NSGA-II


def test_nondominated_ranks_by_hand():
    pts = np.array([[3, 1], [1, 3], [2, 2], [1, 1], [0, 0], [2, 2], [0.5, 0.5], [3, 0]])
    # [3, 0] is dominated by [3, 1] only, so it sits beside [1, 1] in the second front
    assert nondominated_ranks(pts).tolist() == [0, 0, 0, 1, 3, 0, 2, 1]
    assert nondominated_ranks(np.array([[1.0, 1.0]])).tolist() == [0]
    # every rank-r row is dominated by some rank-(r-1) row and by none of rank >= r
    rng = np.random.default_rng(0)
    p = rng.integers(0, 6, size=(40, 3)).astype(float)
    ranks = nondominated_ranks(p)
    assert np.array_equal(ranks == 0, pareto_mask(p))
    for r in range(1, ranks.max() + 1):
        left = ranks >= r
        assert np.array_equal(ranks[left] == r, pareto_mask(p[left]))


def test_crowding_distance_by_hand():
    front = np.array([[0, 4], [1, 3.5], [3, 1], [4, 0]])
    d = crowding_distance(front)
    # objective 0 (range 4): rows 1, 2 get (3-0)/4, (4-1)/4; objective 1 (range 4): row 2
    # sits between 0 and 3.5, row 1 between 1 and 4
    assert d[0] == d[3] == np.inf
    assert d[1] == pytest.approx(0.75 + 0.75)
    assert d[2] == pytest.approx(0.75 + 0.875)
    # an objective with zero range adds nothing; two points or fewer are all boundaries
    assert crowding_distance(np.array([[0, 1], [1, 1], [2, 1]]))[1] == pytest.approx(1.0)
    assert crowding_distance(np.array([[0, 1], [1, 0]])).tolist() == [np.inf, np.inf]


def test_nsga2_selection_keeps_first_fronts_then_cuts_by_crowding():
    front0 = [[10, 0], [0, 10], [6, 6]]
    front1 = [[5, 1], [4, 3], [1, 5], [3.5, 3.6]]  # each dominated by [6, 6]; none dominates another
    pts = np.array(front1 + front0)  # the first front last: selection must not care about order
    ranks, crowd = nsga2_scores(pts)
    assert ranks.tolist() == [1, 1, 1, 1, 0, 0, 0]
    assert nsga2_select(pts, 3) == [4, 5, 6]  # exactly the first front
    # front1's boundaries ([5, 1] and [1, 5]) are infinitely crowded: they come next
    assert nsga2_select(pts, 5) == [0, 2, 4, 5, 6]
    # then the larger interior crowding (ranges 4 and 4): [4, 3] gets (5 - 3.5)/4 + (3.6 - 1)/4,
    # [3.5, 3.6] gets (4 - 1)/4 + (5 - 3)/4
    assert crowd[1] == pytest.approx(0.375 + 0.65) and crowd[3] == pytest.approx(0.75 + 0.5)
    assert nsga2_select(pts, 6) == [0, 2, 3, 4, 5, 6]
    assert nsga2_select(pts, 10) == list(range(7))
    # equal rank and crowding: the earlier row wins
    twins = np.array([[0, 2], [2, 0], [1, 1], [1, 1]])
    assert nsga2_select(twins, 3) == [0, 1, 2]


def test_tournament_prefers_lower_rank():
    pts = np.array([[0, 0], [5, 5], [1, 1], [3, 3], [2, 2]])  # a chain: ranks 4, 0, 3, 1, 2
    ranks, crowd = nsga2_scores(pts)
    assert ranks.tolist() == [4, 0, 3, 1, 2]
    pos = preference_positions(ranks, crowd)
    rng = np.random.default_rng(1)
    counts = np.bincount([tournament_winner(pos, 4, rng) for _ in range(3000)], minlength=5)
    assert counts[1] > counts[3] > counts[4] > counts[2] > counts[0]
    # pairs: two distinct entrants, the better placed first, never the same pair twice...
    used: set = set()
    pairs = [tournament_pair(pos, 4, used, rng) for _ in range(10)]
    assert all(a != b and pos[a] < pos[b] for a, b in pairs)
    assert len({tuple(sorted(p)) for p in pairs}) == 10 == len(used)  # all 10 pairs of 5
    # ...until every pair has been used: then pairs repeat
    again = tournament_pair(pos, 4, used, rng)
    assert len(used) == 1 and tuple(sorted(again)) in {tuple(sorted(p)) for p in pairs}
    # the first pair is more often the best placed entrants
    firsts = [tournament_pair(pos, 4, set(), rng) for _ in range(2000)]
    assert sum(p == (1, 3) for p in firsts) > sum(p == (4, 2) for p in firsts) > sum(p == (2, 0) for p in firsts)


def test_crossover_critic_rule():
    ranks = np.array([0, 0, 1, 1])
    kinds = [0, 1, 1, 0]
    rng = np.random.default_rng(0)
    assert crossover_critic(0, 2, ranks, kinds, 2, rng) == 1  # types differ: the worse parent's
    assert crossover_critic(1, 3, ranks, kinds, 2, rng) == 0
    assert crossover_critic(1, 2, ranks, kinds, 2, rng) == 1  # same type, ranks differ: that type
    assert crossover_critic(0, 3, ranks, kinds, 2, rng) == 0
    assert crossover_critic(2, 1, ranks, kinds, 2, rng) == 1
    assert crossover_critic(0, 1, ranks, [0, 0, 1, 1], 2, rng) == 1  # same type and rank: the other objective
    assert crossover_critic(2, 3, ranks, [1, 1, 1, 1], 2, rng) == 0
    drawn = {crossover_critic(0, 1, ranks, [1, 1, 1, 1], 3, rng) for _ in range(50)}
    assert drawn == {0, 2}  # with three objectives: either other one


def test_archive_update():
    archive = np.array([[3.0, 1.0], [1.0, 3.0]])
    new = np.array([[4.0, 1.0], [0.5, 0.5], [2.0, 2.0], [1.0, 3.0]])
    keep, enter = archive_update(archive, new)
    assert keep.tolist() == [False, True]  # [3, 1] is dominated by the new [4, 1]
    assert enter.tolist() == [True, False, True, True]  # a copy of an archived point joins too
    keep, enter = archive_update(np.zeros((0, 2)), np.array([[1.0, 0.0], [0.0, 0.0]]))
    assert keep.tolist() == [] and enter.tolist() == [True, False]


# ------------------------------------------------------------------------ generation loop


@pytest.fixture(scope="module")
def hopper():
    env = make_env("mo-hopper-2obj-v5", CAP)
    yield env, env_spec(env, "mo-hopper-2obj-v5", CAP)
    env.close()


def synthetic_run(spec, seed: int = 0, **over) -> MopderlRun:
    """A run over random starting actors and RL agents whose buffers hold 300 random rows."""
    td3 = TD3Params(**TD3)
    cfg = MopderlParams(**(MOPDERL | over)).resolved(spec.env_id)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(5)
        mk = lambda: Actor(spec.obs_dim, spec.act_dim, [16], spec.action_low, spec.action_high)  # noqa: E731
        starts = [StartingActor(i % 2, f"pop{i // 2}", mk()) for i in range(6)]
        agents = []
        rng = np.random.default_rng(9)
        for k in range(2):
            actor, critic = mk(), CriticEnsemble(spec.obs_dim, spec.act_dim, [16], 4)
            n = 300
            rows = {
                "obs": rng.normal(size=(n, spec.obs_dim)).astype(np.float32),
                "action": rng.uniform(-1, 1, size=(n, spec.act_dim)).astype(np.float32),
                "reward": rng.normal(size=(n, 2)).astype(np.float32),
                "next_obs": rng.normal(size=(n, spec.obs_dim)).astype(np.float32),
                "terminated": np.zeros(n, bool),
                "truncated": np.zeros(n, bool),
                "episode": np.repeat(np.arange(10), 30),
                "episode_step": np.tile(np.arange(30), 10).astype(np.int32),
            }
            agents.append(AgentInit(k, actor, copy.deepcopy(actor), critic, copy.deepcopy(critic), [0, 1], rows))
    return MopderlRun(spec, td3, cfg, seed, starts, agents)


def test_rl_agents_update_in_the_resolved_precision(hopper):
    """mopderl.precision reaches both RL agents' updates (pipeline/core/precision.py); bf16
    updates stay finite with fp32 master weights."""
    _, spec = hopper
    assert all(a.learner.update.precision == "fp32" for a in synthetic_run(spec).agents)
    run = synthetic_run(spec, precision="bf16")
    assert all(a.learner.update.precision == "bf16" for a in run.agents)
    learner = run.agents[0].learner
    before = learner.networks()[2].weights[1].clone()
    learner.train(4)
    learner.check_finite(full=True)
    critic = learner.networks()[2]
    assert critic.weights[1].dtype == torch.float32 and not torch.equal(critic.weights[1], before)


def test_generation_counts_every_frame(hopper):
    env, spec = hopper
    run = synthetic_run(spec, eval_episodes=2, mutation_prob=0.5, rl_updates_per_frame=0.2)
    lengths = []
    rec = run.initialize(env, lambda ep: lengths.append(ep.length))
    assert len(lengths) == 6 * 2 and rec.frames == run.frames == sum(lengths)
    assert len(run.members) == 6 and [m.policy_name for m in run.members] == [
        "pop0",
        "pop0",
        "pop1",
        "pop1",
        "pop2",
        "pop2",
    ]
    assert all(m.origin == "specialist" and m.objective == i % 2 for i, m in enumerate(run.members))
    assert [m.env_samples for m in run.members] == list(np.cumsum(lengths)[1::2])  # frames once each was evaluated
    for ag in run.agents:  # the starting evaluation fed both buffers, before any update
        assert ag.buffer.size == 300 + run.frames and ag.added == run.frames and ag.updates == 0

    total_new = 0
    for g in (1, 2):
        before = run.frames
        start = len(lengths)
        sizes = [ag.buffer.size for ag in run.agents]
        pop_before = [ind.uid for ind in run.population]
        rec = run.step_generation(env, lambda ep: lengths.append(ep.length))
        eps = lengths[start:]
        n_new = rec.new_individuals
        total_new += n_new
        # children + one per agent + mutated clones (some) + one clone per RL actor
        n_pop = len(pop_before)
        assert 3 + 2 + 2 <= n_new <= 3 + 2 + (n_pop + 5) + 2
        assert len(eps) == n_new * 2 + 2  # every new individual twice, and both RL episodes
        assert rec.frames == run.frames == before + sum(eps)
        eval_frames, rl0, rl1 = sum(eps[:-2]), eps[-2], eps[-1]
        # evaluations went to both buffers; each RL episode only to its own agent's
        assert run.agents[0].buffer.size == sizes[0] + eval_frames + rl0
        assert run.agents[1].buffer.size == sizes[1] + eval_frames + rl1
        for ag in run.agents:
            assert ag.updates == int(0.2 * ag.added)  # updates track the frames it received
        assert rec.updates == [ag.updates for ag in run.agents]
        assert len(run.population) == 4 and rec.generation == g
        assert len(set(ind.uid for ind in run.population)) == 4
    assert len(set(lengths)) > 1 and max(lengths) <= CAP  # hopper falls: lengths vary, all counted
    assert run.frames == sum(lengths)
    # the archive: non-dominated among everything ever evaluated; its phase-2 entries are members
    arch = run.archive_returns()
    assert pareto_mask(arch).all()
    later = run.members[6:]
    assert all(m.origin == "mopderl" and m.iteration in (1, 2) and m.objective is None for m in later)
    assert [m.iteration for m in later] == sorted(m.iteration for m in later)
    assert all(p < i + 6 for i, m in enumerate(later) for p in m.parents)  # parents joined earlier
    every = np.array([m.returns for m in run.members])
    assert all(pareto_mask(np.vstack([arch, every]))[: len(arch)])  # no member dominates the archive
    envs = [m.env_samples for m in run.members]
    assert envs == sorted(envs) and envs[-1] <= run.frames


def same_members(a, b) -> None:
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert (
            x.origin,
            x.objective,
            x.iteration,
            x.parents,
            x.returns,
            x.returns_std,
            x.env_samples,
            x.policy_name,
        ) == (y.origin, y.objective, y.iteration, y.parents, y.returns, y.returns_std, y.env_samples, y.policy_name)
        assert all(torch.equal(x.actor[k], y.actor[k]) for k in x.actor)


def test_checkpoint_resume_is_bitwise(hopper):
    env, spec = hopper
    full = synthetic_run(spec, seed=3)
    full.initialize(env)
    for _ in range(3):
        full.step_generation(env)

    part = synthetic_run(spec, seed=3)
    part.initialize(env)
    part.step_generation(env)
    buf = io.BytesIO()
    torch.save(part.state_dict(), buf)
    state = torch.load(io.BytesIO(buf.getvalue()), weights_only=True)
    resumed = synthetic_run(spec, seed=3)
    resumed.load_state_dict(state)
    for _ in range(2):
        resumed.step_generation(env)

    same_members(full.members, resumed.members)
    assert (full.frames, full.episodes, full.generation) == (resumed.frames, resumed.episodes, resumed.generation)
    assert [r.__dict__ for r in full.history] == [r.__dict__ for r in resumed.history]
    for a, b in zip(full.agents, resumed.agents):
        for name in ("actor", "actor_target", "critic", "critic_target"):
            sa, sb = getattr(a.learner.state, name).state_dict(), getattr(b.learner.state, name).state_dict()
            assert all(torch.equal(sa[k], sb[k]) for k in sa)
        assert a.updates == b.updates and torch.equal(a.buffer.rows, b.buffer.rows)
    assert [i.uid for i in full.population] == [i.uid for i in resumed.population]
    with pytest.raises(ValueError, match="seed"):
        synthetic_run(spec, seed=4).load_state_dict(state)


# ---------------------------------------------------------------------------------- stage


@pytest.fixture(scope="module")
def specialists(tmp_path_factory, write_params):
    """Tiny PDERL specialists of seed 0 (both objectives), made by the real train_pderl stage."""
    d = tmp_path_factory.mktemp("pderl")
    over = {"env": {"max_episode_steps": CAP}, "td3": TD3, "train_pderl": PDERL}
    params = write_params(d, over)
    app = typer.Typer()
    app.command()(train_pderl_stage)
    res = CliRunner().invoke(app, ["--seed", "0", "--out", str(d / "seed0"), "--params", str(params)])
    assert res.exit_code == 0, res.output
    return d / "seed0"


@pytest.fixture
def stage(write_params, specialists):
    """Invoke the mopderl stage in this process: stage(directory, overrides, seed) -> Result."""
    app = typer.Typer()
    app.command()(mopderl_stage)

    def invoke(d: Path, overrides=None, seed: int = 0, source: Path | None = None):
        over = {"env": {"max_episode_steps": CAP}, "td3": TD3, "mopderl": MOPDERL} | (overrides or {})
        params = write_params(d, over)
        args = [
            "--seed",
            str(seed),
            "--specialists",
            str(source or specialists),
            "--out",
            str(d / "out"),
            "--resume-dir",
            str(d / "resume"),
            "--params",
            str(params),
        ]
        return CliRunner().invoke(app, args)

    return invoke


def read_outputs(out: Path):
    members, meta = load_population(out / "population.pt", ["env_id", "seed", "method"])
    return members, meta, (out / "history.csv").read_text()


def test_stage_end_to_end_and_resume_after_kill(tmp_path, stage, monkeypatch):
    res = stage(tmp_path / "full")
    assert res.exit_code == 0, res.output
    out = tmp_path / "full" / "out"
    members, meta, hist = read_outputs(out)
    assert sorted(p.name for p in out.iterdir()) == ["history.csv", "population.pt"]
    assert not (tmp_path / "full" / "resume" / "mopderl" / "seed0").exists()  # progress cleared
    assert meta["method"] == "mopderl" and meta["seed"] == 0 and meta["env_id"] == "mo-halfcheetah-v5"
    assert meta["params"]["mopderl"]["population_size"] == 4 and "provenance" not in meta
    assert meta["params"]["td3"] == TD3Params(**TD3).model_dump()  # the RL agents' section, whole
    assert meta["action_low"] == [-1.0] * 6 and meta["n_objectives"] == 2
    # the starting population: each specialist's population actors ("rl" is the RL agent)
    starts = [m for m in members if m.origin == "specialist"]
    assert [(m.objective, m.policy_name) for m in starts] == [(k, f"pop{i}") for k in (0, 1) for i in range(3)]
    assert members[: len(starts)] == starts and all(m.iteration == 0 and m.parents == [] for m in starts)
    later = members[len(starts) :]
    assert later and all(m.origin == "mopderl" and m.iteration >= 1 and m.target_weight is None for m in later)
    assert all(m.hidden_sizes == [16] and m.eval_episodes == 1 and len(m.returns) == 2 for m in members)
    samples = [m.env_samples for m in members]
    assert samples == sorted(samples) and samples[0] == CAP  # cumulative phase-2 frames
    rows = list(csv.DictReader(io.StringIO(hist)))
    assert list(rows[0]) == [
        "generation",
        "env_frames",
        "new_individuals",
        "archive_size",
        "front_size",
        "archive_hv_norm",
    ]
    assert [int(r["generation"]) for r in rows] == list(range(len(rows))) and len(rows) >= 3
    assert int(rows[0]["env_frames"]) == 6 * CAP and int(rows[-1]["env_frames"]) >= MOPDERL["total_frames"]
    assert int(rows[-2]["env_frames"]) < MOPDERL["total_frames"]  # stopped at the first generation past the budget
    assert max(m.iteration for m in later) == int(rows[-1]["generation"])
    assert all(0 <= float(r["archive_hv_norm"]) <= 1 and int(r["front_size"]) <= 4 for r in rows)

    # Killed in generation 2 (generation 1 checkpointed), then rerun: the same artifacts.
    real = MopderlRun.step_generation
    calls = {"n": 0}

    class Killed(Exception):
        pass

    def dies_second(self, env, on_episode=None):
        calls["n"] += 1
        if calls["n"] == 2:
            raise Killed
        return real(self, env, on_episode)

    monkeypatch.setattr(MopderlRun, "step_generation", dies_second)
    res = stage(tmp_path / "killed")
    assert isinstance(res.exception, Killed)
    assert not (tmp_path / "killed" / "out").exists()
    progress = tmp_path / "killed" / "resume" / "mopderl" / "seed0"
    assert torch.load(progress / "state.pt", weights_only=True)["state"]["counters"]["generation"] == 1
    monkeypatch.setattr(MopderlRun, "step_generation", real)
    res = stage(tmp_path / "killed")
    assert res.exit_code == 0, res.output
    assert "resuming from generation 1" in res.output
    resumed, rmeta, rhist = read_outputs(tmp_path / "killed" / "out")
    same_members(members, resumed)
    assert rhist == hist and rmeta["params"] == meta["params"]

    # SIGTERM during generation 2, no periodic checkpoint due: the stage checkpoints once that
    # generation ends, says so in one line and exits with 143; the rerun resumes to the same artifacts.
    def sigterm_in_second(self, env, on_episode=None):
        calls["n"] += 1
        if calls["n"] == 2:
            os.kill(os.getpid(), signal.SIGTERM)  # deferred by the stage until its next safe point
        return real(self, env, on_episode)

    calls["n"] = 0
    rare = {"mopderl": MOPDERL | {"checkpoint_every": 1000}}  # not in the fingerprint
    monkeypatch.setattr(MopderlRun, "step_generation", sigterm_in_second)
    res = stage(tmp_path / "term", rare)
    assert res.exit_code == 143, res.output
    state = tmp_path / "term" / "resume" / "mopderl" / "seed0" / "state.pt"
    line = f"mopderl seed 0: SIGTERM: checkpoint written at generation 2 ({state}); rerun to resume"
    assert line in res.output.splitlines() and not (tmp_path / "term" / "out").exists()
    monkeypatch.setattr(MopderlRun, "step_generation", real)
    res = stage(tmp_path / "term", rare)
    assert res.exit_code == 0 and "resuming from generation 2" in res.output, res.output
    resumed, rmeta, rhist = read_outputs(tmp_path / "term" / "out")
    same_members(members, resumed)
    assert rhist == hist and rmeta["params"] == meta["params"]

    # Progress of other params is not trusted: the run starts over.
    calls["n"] = 0
    monkeypatch.setattr(MopderlRun, "step_generation", dies_second)
    stage(tmp_path / "stale")
    monkeypatch.setattr(MopderlRun, "step_generation", real)
    res = stage(tmp_path / "stale", {"mopderl": MOPDERL | {"mutation_std": 0.1}})
    assert res.exit_code == 0 and "resuming" not in res.output


def test_stage_checks_the_specialists(tmp_path, stage, specialists):
    res = stage(tmp_path / "a", seed=1)  # seed-0 specialists given as seed 1
    assert res.exit_code == 2 and "seed" in res.output and "expected 1" in res.output
    swapped = tmp_path / "swapped"
    shutil.copytree(specialists / "obj0", swapped / "obj1")
    shutil.copytree(specialists / "obj1", swapped / "obj0")
    res = stage(tmp_path / "b", source=swapped)
    assert res.exit_code == 2 and "objective" in res.output
    mixed = tmp_path / "mixed"
    shutil.copytree(specialists, mixed)
    shutil.copy(specialists / "obj1" / "policy.pt", mixed / "obj0" / "policy.pt")  # another slot's RL actor
    res = stage(tmp_path / "c", source=mixed)
    assert res.exit_code == 2 and "policy.pt" in res.output
    assert not any((tmp_path / d / "out").exists() for d in "abc")
