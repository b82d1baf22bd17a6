"""PDERL specialists (pipeline/specialists/pderl.py, stages/train_pderl.py).

The genetic operators on hand-checkable networks; elitism, frame accounting and checkpoint
determinism of the generation loop; and the real stage end to end on a tiny preset, killed
after two generations and resumed to the same bits as an uninterrupted run.
"""

from __future__ import annotations

import copy
import io
import math
import os
import signal
from pathlib import Path

import numpy as np
import pytest
import torch
import typer
from typer.testing import CliRunner

import pipeline.params
from pipeline.core.buffer import load_buffer
from pipeline.core.checkpoint import load_critics, load_policy
from pipeline.core.envs import env_spec, make_env
from pipeline.core.nets import Actor
from pipeline.core.policyset import load_policy_set
from pipeline.params.td3 import TD3Params
from pipeline.params.train_pderl import TrainPderlParams
from pipeline.specialists.pderl import (
    Individual,
    PderlRun,
    StateRing,
    action_sensitivity,
    distillation_crossover,
    evolve,
    proximal_mutation,
    tournament,
    train_pderl,
)
from stages.train_pderl import CHECKPOINT_PREFIX
from stages.train_pderl import train_pderl as train_pderl_stage

CAP = 30
TD3 = {"learning_starts": 100, "buffer_size": 5000, "batch_size": 32, "hidden_sizes": [16, 16]}
PDERL = {
    "total_frames": 400,
    "population_size": 3,
    "mini_buffer_size": 200,
    "crossover_transitions": 64,
    "crossover_batch_size": 32,
    "crossover_epochs": 2,
    "mutation_states": 32,
    "checkpoint_every": 1,
    "device": "cpu",
}


def tiny_actor(hidden: list[int], w1, b1, w2, b2) -> Actor:
    actor = Actor(len(w1[0]), len(w2), hidden, [-1.0] * len(w2), [1.0] * len(w2))
    with torch.no_grad():
        actor.net[0].weight.copy_(torch.tensor(w1))
        actor.net[0].bias.copy_(torch.tensor(b1))
        actor.net[2].weight.copy_(torch.tensor(w2))
        actor.net[2].bias.copy_(torch.tensor(b2))
    return actor


def ring_of(states: np.ndarray, capacity: int | None = None) -> StateRing:
    ring = StateRing(capacity or len(states), states.shape[1])
    ring.extend(states)
    return ring


# --------------------------------------------------------------------- proximal mutation


def hand_net() -> tuple[Actor, torch.Tensor]:
    """a = tanh(0.1 h1 + 0.5 h2), h1 = relu(x0 + x1), h2 = relu(x0 + x1 - 100) (dead), on 10
    copies of x = (10, 0.1): h1 = 10.1, a = tanh(1.01)."""
    actor = tiny_actor([2], [[1.0, 1.0], [1.0, 1.0]], [0.0, -100.0], [[0.1, 0.5]], [0.0])
    return actor, torch.tensor([[10.0, 0.1]]).repeat(10, 1)


def test_action_sensitivity_by_hand():
    actor, states = hand_net()
    d = 1 - math.tanh(1.01) ** 2  # da/dpre
    s1, s2 = action_sensitivity(actor, states)
    # da/dw1[0, i] = d * 0.1 * x_i, summed over 10 states; the dead unit's weights move nothing
    assert torch.allclose(s1, torch.tensor([[10 * d * 0.1 * 10, 10 * d * 0.1 * 0.1], [0.0, 0.0]]), rtol=1e-5)
    assert torch.allclose(s2, torch.tensor([[10 * d * 10.1, 0.0]]), rtol=1e-5)


def test_proximal_mutation_moves_sensitive_weights_less():
    actor, states = hand_net()
    before = copy.deepcopy(actor)
    std = 0.05
    deltas = proximal_mutation(actor, states, std, torch.Generator().manual_seed(3), min_sensitivity=0.01)
    # the documented draw: one randn per weight matrix, in parameter order, on the CPU
    g = torch.Generator().manual_seed(3)
    noise = [torch.randn(2, 2, generator=g), torch.randn(1, 2, generator=g)]
    d = 1 - math.tanh(1.01) ** 2
    sens1 = torch.tensor([[d * 10, d * 0.1], [1.0, 1.0]])  # exact zeros divide by 1
    sens2 = torch.tensor([[d * 101, 1.0]])
    assert torch.allclose(deltas[0], noise[0] * std / sens1, rtol=1e-5)
    assert torch.allclose(deltas[1], noise[1] * std / sens2, rtol=1e-5)
    assert torch.equal(actor.net[0].weight, before.net[0].weight + deltas[0])
    assert torch.equal(actor.net[0].bias, before.net[0].bias)  # biases are not mutated
    assert torch.equal(actor.net[2].bias, before.net[2].bias)
    # over many draws, w[0,0] (100x as sensitive as w[0,1]) moves ~100x less
    moves = []
    for seed in range(200):
        a, st = hand_net()
        moves.append(proximal_mutation(a, st, std, torch.Generator().manual_seed(seed))[0][0].abs())
    mean = torch.stack(moves).mean(0)
    assert 50 < float(mean[1] / mean[0]) < 200


def test_proximal_mutation_clamps_tiny_sensitivity():
    actor, _ = hand_net()
    states = torch.tensor([[1e-4, 1e-4]])  # h1 = 2e-4: every live sensitivity far below 0.01
    deltas = proximal_mutation(actor, states, 0.05, torch.Generator().manual_seed(0), min_sensitivity=0.01)
    g = torch.Generator().manual_seed(0)
    n1 = torch.randn(2, 2, generator=g)
    expect = torch.stack([n1[0] * 0.05 / 0.01, n1[1] * 0.05])  # live row clamped to 0.01, dead row / 1
    assert torch.allclose(deltas[0], expect, rtol=1e-5)


# -------------------------------------------------------------------- distillation crossover


def constant_actor(value: float, obs_dim: int = 2, hidden: int = 16, seed: int = 0) -> Actor:
    torch.manual_seed(seed)
    actor = Actor(obs_dim, 1, [hidden], [-1.0], [1.0])
    with torch.no_grad():
        actor.net[2].weight.zero_()
        actor.net[2].bias.fill_(math.atanh(value))
    return actor


def toy_critic(obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """Q(s, a) = a * sign(s_0): positive actions are better where s_0 > 0, negative elsewhere."""
    return action[:, 0] * torch.sign(obs[:, 0])


def test_distillation_crossover_follows_the_better_parent():
    rng = np.random.default_rng(0)
    states = rng.uniform(1, 2, size=(128, 2)).astype(np.float32) * rng.choice([-1, 1], size=(128, 1)).astype(np.float32)
    a, b = constant_actor(0.5, seed=1), constant_actor(-0.5, seed=2)
    a_before, b_before = copy.deepcopy(a), copy.deepcopy(b)
    buf_a, buf_b = ring_of(states[:64]), ring_of(states[64:])
    cfg = TrainPderlParams(
        crossover_transitions=64,
        crossover_epochs=150,
        crossover_batch_size=32,
        crossover_lr=1e-2,
        crossover_action_penalty=0.0,
    )
    child, used = distillation_crossover(a, b, buf_a, buf_b, toy_critic, cfg, np.random.default_rng(1))
    assert np.array_equal(used, np.concatenate([states[:64], states[64:]]))  # A's latest, then B's
    with torch.no_grad():
        out = child(torch.from_numpy(states))[:, 0]
    positive = torch.from_numpy(states[:, 0] > 0)
    # where s_0 > 0 the critic prefers A's +0.5, elsewhere B's -0.5: the child learnt both
    assert (out[positive] - 0.5).abs().max() < 0.1
    assert (out[~positive] + 0.5).abs().max() < 0.1
    # the parents are untouched
    for parent, before in ((a, a_before), (b, b_before)):
        for x, y in zip(parent.state_dict().values(), before.state_dict().values()):
            assert torch.equal(x, y)


def test_tournament_prefers_the_fittest():
    ranked = [4, 2, 0, 1, 3]  # slot 4 best
    wins = tournament(ranked, 400, 3, np.random.default_rng(0))
    assert len(wins) == len(set(wins)) and set(wins) <= set(ranked)  # unique winners
    draws = np.random.default_rng(1)
    counts = np.bincount([tournament(ranked, 1, 3, draws)[0] for _ in range(2000)], minlength=5)
    assert counts[4] > counts[2] > counts[0] > counts[1] > counts[3]  # ordered as the ranking


# -------------------------------------------------------------------------------- evolve


def test_elites_survive_evolution_unchanged():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    pop = []
    for i in range(10):
        ring = ring_of(rng.normal(size=(50, 3)).astype(np.float32), capacity=100)
        pop.append(Individual(Actor(3, 2, [8], [-1, -1], [1, 1]), ring, fitness=float(i)))
    before = copy.deepcopy(pop)
    cfg = TrainPderlParams(
        population_size=10,
        elite_fraction=0.2,
        mini_buffer_size=100,
        crossover_transitions=20,
        crossover_batch_size=10,
        crossover_epochs=1,
        mutation_states=16,
        mutation_prob=1.0,
    )
    report = evolve(pop, lambda o, a: a.sum(dim=1), cfg, np.random.default_rng(1), torch.Generator().manual_seed(0))
    assert report.elites == [9, 8]
    for slot in report.elites:
        assert pop[slot].fitness == before[slot].fitness
        for x, y in zip(pop[slot].actor.state_dict().values(), before[slot].actor.state_dict().values()):
            assert torch.equal(x, y)
        assert np.array_equal(pop[slot].ring.chronological(), before[slot].ring.chronological())
    # every other slot was mutated (probability 1) and lost its fitness until evaluated again
    assert sorted(report.mutated) == [s for s in range(10) if s not in report.elites]
    assert all(pop[s].fitness is None for s in report.mutated)
    # children filled exactly the slots no survivor (or elite copy) holds, from survivor parents
    survivors = set(report.elites) | set(report.selected)
    assert set(report.children) == set(range(10)) - survivors - set(report.copies)
    assert all(
        a in survivors and b in survivors and before[a].fitness >= before[b].fitness
        for a, b in report.children.values()
    )
    for slot, (a, b) in report.children.items():  # its mini buffer: the parents' latest states
        assert np.array_equal(
            pop[slot].ring.chronological(), np.concatenate([before[a].ring.latest(20), before[b].ring.latest(20)])
        )


# ----------------------------------------------------------------------- generation loop


def tiny_cfgs(**pderl):
    return TD3Params(**TD3), TrainPderlParams(**(PDERL | pderl))


@pytest.fixture(scope="module")
def hopper():
    env = make_env("mo-hopper-2obj-v5", CAP)
    yield env, env_spec(env, "mo-hopper-2obj-v5", CAP)
    env.close()


def test_generation_keeps_elites_and_counts_every_frame(hopper):
    env, spec = hopper
    td3, cfg = tiny_cfgs(eval_episodes=2)
    run = PderlRun(spec, td3, cfg, 0, 7)
    lengths = []
    for _ in range(3):
        before = [copy.deepcopy(ind.actor) for ind in run.population]
        rec = run.step_generation(env, lambda ep: lengths.append(ep.length))
        kept = [i for i, ind in enumerate(run.population) if ind.fitness is not None]
        assert any(run.population[i].fitness == rec.best for i in kept)  # the elite kept its evaluation
        for i in kept:  # and whatever kept its fitness kept its weights
            assert all(torch.equal(x, y) for x, y in zip(run.population[i].actor.parameters(), before[i].parameters()))
    rl_fitness = run.evaluate_final(env, lambda ep: lengths.append(ep.length))
    # hopper falls: episodes of many lengths, each counted in full
    assert len(set(lengths)) > 1 and max(lengths) <= CAP
    per_gen = cfg.population_size * cfg.eval_episodes + 1
    assert len(lengths) == 3 * per_gen + (cfg.population_size + 1) * cfg.eval_episodes
    assert run.frames == sum(lengths) == run.buffer.size  # every frame, and every frame in the buffer
    assert [r.frames for r in run.history] == [sum(lengths[: per_gen * g]) for g in (1, 2, 3)]
    assert run.updates == run.history[-1].frames - td3.learning_starts  # one update per frame past the start
    assert run.episodes == len(lengths) and np.isfinite(rl_fitness)
    # the buffer's episode bookkeeping: consecutive episode ids, step counters restarting at 0
    ep = run.buffer.host["episode"][0, : run.buffer.size]
    assert np.array_equal(np.bincount(ep), lengths)


def test_checkpoint_resume_is_bitwise(hopper):
    env, spec = hopper
    td3, cfg = tiny_cfgs()
    full = train_pderl(env, spec, td3, cfg, 1, 3)

    class Killed(Exception):
        pass

    saved = {}

    def kill_after_two(run, rec):
        if rec.generation == 2:
            buf = io.BytesIO()
            torch.save(run.state_dict(), buf)
            saved["state"] = buf.getvalue()
            raise Killed

    with pytest.raises(Killed):
        train_pderl(env, spec, td3, cfg, 1, 3, on_generation=kill_after_two)
    state = torch.load(io.BytesIO(saved["state"]), weights_only=True)
    resumed = train_pderl(env, spec, td3, cfg, 1, 3, state=state)
    assert resumed.frames == full.frames and resumed.updates == full.updates
    assert resumed.fitness == full.fitness and resumed.rl_fitness == full.rl_fitness
    nets = lambda r: [*r.actors, r.actor, r.actor_target, r.critic, r.critic_target]  # noqa: E731
    for x, y in zip(nets(full), nets(resumed)):
        assert all(torch.equal(a, b) for a, b in zip(x.state_dict().values(), y.state_dict().values()))
    assert all(np.array_equal(full.buffer[k], resumed.buffer[k]) for k in full.buffer)
    with pytest.raises(ValueError, match="seed"):
        PderlRun(spec, td3, cfg, 1, 4).load_state_dict(state)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
@pytest.mark.parametrize("graphs", [True, False], ids=["cuda-graphs", "cuda-eager"])
def test_runs_on_cuda_and_resumes(hopper, graphs):
    """On CUDA (the RL agent's buffer on the GPU, its updates as CUDA graphs or eager): one
    update per frame past the start, the agent learns, and a run restored after generation 2
    keeps its history and goes on to the budget. (Not compared bit for bit with the
    uninterrupted run: CUDA promises reproducibility only up to its kernels, and the
    population's discrete choices can amplify a last-bit difference.)"""
    env, spec = hopper
    td3 = TD3Params(**(TD3 | {"cuda_graphs": graphs}))
    cfg = TrainPderlParams(**(PDERL | {"device": "cuda"}))
    saved = {}

    def keep_two(run, rec):
        if rec.generation == 2:
            saved["state"] = torch.load(io.BytesIO(_saved_bytes(run)), weights_only=True)

    full = train_pderl(env, spec, td3, cfg, 1, 3, device="cuda", on_generation=keep_two)
    assert full.updates == full.history[-1].frames - td3.learning_starts
    fresh = PderlRun(spec, td3, cfg, 1, 3, device="cuda").agent.networks()[0]
    assert not all(torch.equal(a, b) for a, b in zip(full.actor.parameters(), fresh.parameters()))
    assert np.isfinite(full.rl_fitness) and all(np.isfinite(full.fitness))
    resumed = train_pderl(env, spec, td3, cfg, 1, 3, device="cuda", state=saved["state"])
    assert resumed.history[:2] == full.history[:2] and len(resumed.history) > 2
    assert resumed.frames >= cfg.total_frames and resumed.updates == resumed.history[-1].frames - td3.learning_starts
    assert np.isfinite(resumed.rl_fitness)


def _saved_bytes(run) -> bytes:
    buf = io.BytesIO()
    torch.save(run.state_dict(), buf)
    return buf.getvalue()


# ---------------------------------------------------------------------------------- stage


@pytest.fixture
def stage(monkeypatch, write_params):
    """Invoke the stage in this process on the tiny preset: stage(directory, overrides) -> Result."""
    assert "train_pderl" in pipeline.params.KNOWN_SECTIONS
    app = typer.Typer()
    app.command()(train_pderl_stage)

    def invoke(d: Path, overrides=None, objective: int | list[int] = 1):
        over = {"env": {"max_episode_steps": CAP}, "td3": TD3, "train_pderl": PDERL} | (overrides or {})
        params = write_params(d, over)
        chosen = [
            a for k in ([objective] if isinstance(objective, int) else objective) for a in ("--objective", str(k))
        ]
        return CliRunner().invoke(app, ["--seed", "0", *chosen, "--out", str(d / "out"), "--params", str(params)])

    return invoke


def artifacts(out: Path) -> dict:
    pset = load_policy_set(out / "policies.pt")
    actor, pmeta = load_policy(out / "policy.pt")
    online, target, cmeta = load_critics(out / "critics.pt")
    data, attrs = load_buffer(out / "buffer.zarr")
    return {
        "pset": pset,
        "actor": actor,
        "pmeta": pmeta,
        "critics": (online, target),
        "cmeta": cmeta,
        "data": data,
        "attrs": attrs,
        "fitness": (out / "fitness.csv").read_text(),
        "policy_obj": torch.load(out / "policy.pt", weights_only=True),
    }


def same_bits(x: dict, y: dict) -> None:
    for a, b in zip(x["pset"].actors + [x["actor"], *x["critics"]], y["pset"].actors + [y["actor"], *y["critics"]]):
        assert all(torch.equal(p, q) for p, q in zip(a.state_dict().values(), b.state_dict().values()))
    for key, value in x["policy_obj"]["actor_target"].items():
        assert torch.equal(value, y["policy_obj"]["actor_target"][key])
    assert x["pset"].fitness == y["pset"].fitness and x["fitness"] == y["fitness"]
    assert all(np.array_equal(x["data"][k], y["data"][k]) for k in x["data"])


def test_stage_end_to_end_and_resume_after_kill(tmp_path, stage, monkeypatch):
    res = stage(tmp_path / "full")
    assert res.exit_code == 0, res.output
    out = tmp_path / "full" / "out" / "obj1"
    assert sorted(p.name for p in out.iterdir()) == [
        "buffer.zarr",
        "critics.pt",
        "fitness.csv",
        "policies.pt",
        "policy.pt",
    ]
    full = artifacts(out)
    pset = full["pset"]
    assert pset.names == ["rl", "pop0", "pop1", "pop2"] and all(isinstance(f, float) for f in pset.fitness)
    assert pset.meta["objective"] == 1 and pset.meta["seed"] == 0 and pset.meta["hidden_sizes"] == [16, 16]
    assert pset.meta["trainer"] == "pderl"
    assert all(
        torch.equal(p, q) for p, q in zip(pset.actors[0].state_dict().values(), full["actor"].state_dict().values())
    )
    cmeta = full["cmeta"]
    assert cmeta["source"] == "joint" and cmeta["objectives"] == [0, 1] and cmeta["buffer_objective"] == 1
    assert set(cmeta["params"]) == {"env", "td3", "train_pderl"}
    assert cmeta["params"]["td3"]["gamma"] == 0.99 and "provenance" not in cmeta
    attrs, data = full["attrs"], full["data"]
    assert attrs["objective"] == 1 and attrs["seed"] == 0 and attrs["max_episode_steps"] == CAP
    assert len(data["obs"]) == pset.meta["env_frames"] >= PDERL["total_frames"]
    rows = full["fitness"].splitlines()
    assert rows[0] == "generation,frames,updates,best,mean,rl_fitness" and rows[-1].startswith("final,")
    assert int(rows[-1].split(",")[1]) == len(data["obs"])

    # Killed after generation 2 (its checkpoint written), then rerun: the same bits.
    real = PderlRun.step_generation
    calls = {"n": 0}

    class Killed(Exception):
        pass

    def dies_third(self, env, on_episode=None):
        calls["n"] += 1
        if calls["n"] == 3:
            raise Killed
        return real(self, env, on_episode)

    monkeypatch.setattr(PderlRun, "step_generation", dies_third)
    res = stage(tmp_path / "killed")
    assert isinstance(res.exception, Killed)
    out = tmp_path / "killed" / "out" / "obj1"
    ckpt = (
        tmp_path / "killed" / ".out.resume" / f"{CHECKPOINT_PREFIX}obj1.pt"
    )  # beside OUT, which DVC deletes before a rerun
    assert ckpt.is_file() and not out.exists()
    monkeypatch.setattr(PderlRun, "step_generation", real)
    res = stage(tmp_path / "killed")
    assert res.exit_code == 0, res.output
    assert "resuming from generation 2" in res.output
    assert not ckpt.exists() and not ckpt.parent.exists()
    same_bits(full, artifacts(out))

    # SIGTERM during generation 2, no periodic checkpoint due: the stage checkpoints once that
    # generation ends, says so in one line and exits with 143; the rerun resumes to the same bits.
    def sigterm_in_second(self, env, on_episode=None):
        calls["n"] += 1
        if calls["n"] == 2:
            os.kill(os.getpid(), signal.SIGTERM)  # deferred by the stage until its next safe point
        return real(self, env, on_episode)

    calls["n"] = 0
    rare = {"train_pderl": PDERL | {"checkpoint_every": 1000}}  # not in the fingerprint
    monkeypatch.setattr(PderlRun, "step_generation", sigterm_in_second)
    res = stage(tmp_path / "term", rare)
    assert res.exit_code == 143, res.output
    ckpt = tmp_path / "term" / ".out.resume" / f"{CHECKPOINT_PREFIX}obj1.pt"
    (line,) = [x for x in res.output.splitlines() if "SIGTERM" in x]
    assert line.startswith("train_pderl seed 0, obj 1 (")
    assert line.endswith(f"): SIGTERM: checkpoint written at generation 2 ({ckpt}); rerun to resume")
    assert calls["n"] == 2 and not (tmp_path / "term" / "out" / "obj1").exists()
    monkeypatch.setattr(PderlRun, "step_generation", real)
    res = stage(tmp_path / "term", rare)
    assert res.exit_code == 0 and "resuming from generation 2" in res.output, res.output
    same_bits(full, artifacts(tmp_path / "term" / "out" / "obj1"))

    # A checkpoint of other params is not trusted: the run starts over.
    calls["n"] = 0
    monkeypatch.setattr(PderlRun, "step_generation", dies_third)
    calls["n"] = 0
    stage(tmp_path / "stale")
    monkeypatch.setattr(PderlRun, "step_generation", real)
    res = stage(tmp_path / "stale", {"train_pderl": PDERL | {"mutation_std": 0.1}})
    assert res.exit_code == 0 and "starting over" in res.output and "resuming" not in res.output


@pytest.fixture
def one_thread():
    """One torch thread, mapex's default. The workers take the stage's count, and two each on a
    2-core machine oversubscribe it (measured several times slower)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def test_side_by_side_processes_give_the_same_artifacts(tmp_path, stage, monkeypatch, one_thread):
    """train_pderl.processes: 2 runs the two objectives' PDERL runs in two worker processes at
    once: each run is the one the stage's own process would make, bit for bit."""
    import stages.common as stage_module  # run_parts starts the workers

    one = stage(tmp_path / "one", objective=[0, 1])
    assert one.exit_code == 0, one.output
    parts = []
    real = stage_module.run_side_by_side
    monkeypatch.setattr(
        stage_module,
        "run_side_by_side",
        lambda fn, args, *a, **k: (parts.append([x[1] for x in args]), real(fn, args, *a, **k)),
    )
    two = stage(tmp_path / "two", {"train_pderl": PDERL | {"processes": 2}}, objective=[0, 1])
    assert two.exit_code == 0, two.output
    assert parts == [[[0], [1]]]  # one worker per objective
    for k in (0, 1):
        same_bits(artifacts(tmp_path / "one" / "out" / f"obj{k}"), artifacts(tmp_path / "two" / "out" / f"obj{k}"))
        assert not (tmp_path / "two" / ".out.resume").exists()


def test_stage_rejects_bad_params(tmp_path, stage):
    res = stage(tmp_path, {"train_pderl": PDERL | {"total_frames": 50}})
    assert res.exit_code == 2 and "td3.learning_starts (100) must be < train_pderl.total_frames (50)" in res.output
    res = stage(tmp_path, {"train_pderl": PDERL | {"population_size": 1}})
    assert res.exit_code == 2 and "train_pderl.population_size" in res.output
    res = stage(tmp_path, objective=2)
    assert res.exit_code == 2 and "objectives 0..1" in res.output
    assert not (tmp_path / "out").exists()
