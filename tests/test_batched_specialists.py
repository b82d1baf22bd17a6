"""Batched specialists: S specialists stacked in one process are each exactly TD3 alone.

Fast-vs-naive: the stacked update against `td3_update` on each specialist separately; the
stacked training loop against one-at-a-time training for the same seeds (same minibatch rows,
same smoothing noise, same artifacts); the CUDA graph path against eager CUDA when a GPU exists.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

import pipeline.specialists.td3 as td3_mod
from pipeline.core.buffer import Batch, StackedReplay, batch_at
from pipeline.core.envs import env_spec, make_env
from pipeline.core.nets import Actor, CriticEnsemble, StackedActor
from pipeline.params.td3 import TD3Params
from pipeline.params.train_specialist import TrainSpecialistParams
from pipeline.specialists.td3 import TD3State, init_stacked, init_td3, run_seeds, stack_td3, stacked_update, td3_update
from pipeline.specialists.td3_learner import TD3Learner
from pipeline.specialists.td3_training import train_specialists

ENV, CAP = "mo-swimmer-v5", 25
CFG = TD3Params(learning_starts=40, batch_size=16, hidden_sizes=[16, 16], buffer_size=70)
RUN = TrainSpecialistParams(total_steps=90, device="cpu")


def spec_of():
    env = make_env(ENV, CAP)
    spec = env_spec(env, ENV, CAP)
    env.close()
    return spec


@pytest.mark.parametrize("secondary", [True, False])
def test_stacked_update_is_td3_update_per_specialist(secondary):
    """Two specialists (objectives 0 and 1) updated stacked vs each by td3_update alone."""
    spec, cfg = spec_of(), CFG.model_copy(update={"secondary_critics": secondary})
    jobs = [(3, 0), (3, 1)]
    stacked = init_stacked(spec, cfg, jobs, torch.device("cpu"))
    singles = []
    for seed, k in jobs:
        torch.manual_seed(run_seeds(seed, k)["torch"])
        singles.append(init_td3(spec, cfg, k, torch.device("cpu")))
    # Same initial weights: each stacked specialist starts where it would alone.
    for s, single in enumerate(singles):
        for a, b in zip(stacked.actor.unstack(s).state_dict().values(), single.actor.state_dict().values()):
            assert torch.equal(a, b)
    g = torch.Generator().manual_seed(0)
    b_, o, a, m = 12, spec.obs_dim, spec.act_dim, spec.n_objectives
    for step in range(6):
        batch = Batch(
            torch.randn(2, b_, o, generator=g),
            torch.rand(2, b_, a, generator=g) * 2 - 1,
            torch.randn(2, b_, m, generator=g),
            torch.randn(2, b_, o, generator=g),
            (torch.rand(2, b_, generator=g) < 0.2).float(),
        )
        # each specialist's smoothing noise from its own generator, as td3_update draws it
        noise_seeds = [100 + 2 * step, 101 + 2 * step]
        noise = torch.stack([torch.randn(b_, a, generator=torch.Generator().manual_seed(x)) for x in noise_seeds])
        update_actor = step % 2 == 1
        stacked_update(stacked, batch, noise, update_actor, gamma=0.99, tau=0.05, policy_noise=0.2, noise_clip=0.5)
        for s, single in enumerate(singles):
            one = Batch(*(f[s] for f in batch))
            td3_update(single, one, update_actor, 0.99, 0.05, 0.2, 0.5, torch.Generator().manual_seed(noise_seeds[s]))
    e = stacked.critic.n_members // 2
    for s, single in enumerate(singles):
        for x, y in zip(stacked.actor.unstack(s).parameters(), single.actor.parameters()):
            torch.testing.assert_close(x, y, rtol=1e-5, atol=1e-6)
        for x, y in zip(stacked.critic.subset(s * e, (s + 1) * e).parameters(), single.critic.parameters()):
            torch.testing.assert_close(x, y, rtol=1e-5, atol=1e-6)
        for x, y in zip(
            stacked.critic_target.subset(s * e, (s + 1) * e).parameters(), single.critic_target.parameters()
        ):
            torch.testing.assert_close(x, y, rtol=1e-5, atol=1e-6)


def record_draws(monkeypatch):
    """Record every minibatch-row draw and smoothing-noise tensor the training loop makes."""
    rows, noises = [], []
    real_gather = StackedReplay.gather
    real_update = td3_mod.stacked_update

    def gather(self, idx):
        rows.append(idx.clone())
        return real_gather(self, idx)

    def update(state, batch, noise, update_actor, **kw):
        noises.append(noise.clone())
        return real_update(state, batch, noise, update_actor, **kw)

    monkeypatch.setattr(StackedReplay, "gather", gather)
    monkeypatch.setattr(td3_mod, "stacked_update", update)
    return rows, noises


def test_batched_training_draws_what_one_at_a_time_draws(monkeypatch):
    spec = spec_of()
    jobs = [(0, 0), (0, 1), (1, 0)]
    rows, noises = record_draws(monkeypatch)
    stacked = train_specialists([make_env(ENV, CAP) for _ in jobs], spec, CFG, RUN, jobs, torch.device("cpu"))
    together = (torch.stack(rows), torch.stack(noises))
    assert together[0].shape == (RUN.total_steps - CFG.learning_starts, 3, CFG.batch_size)
    alone = []
    for s, job in enumerate(jobs):
        rows.clear()
        noises.clear()
        res = train_specialists([make_env(ENV, CAP)], spec, CFG, RUN, [job], torch.device("cpu"))[0]
        assert torch.equal(torch.stack(rows)[:, 0], together[0][:, s]), job
        assert torch.equal(torch.stack(noises)[:, 0], together[1][:, s]), job
        alone.append(res)
    for a, b in zip(stacked, alone):
        assert (a.seed, a.objective) == (b.seed, b.objective)
        # Same draws, same data: the envs saw the same actions to the float (stacked matmuls
        # may differ from S = 1 in the last bits, which this short run does not show).
        np.testing.assert_allclose(a.buffer["obs"], b.buffer["obs"], rtol=1e-5, atol=1e-5)
        for name in ("episode", "episode_step", "terminated", "truncated"):
            assert np.array_equal(a.buffer[name], b.buffer[name]), name
        for x, y in zip(a.actor.parameters(), b.actor.parameters()):
            torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-5)
        assert [r.end_step for r in a.episodes] == [r.end_step for r in b.episodes]
    # Different specialists do draw differently.
    assert not torch.equal(together[0][:, 0], together[0][:, 1])


def test_stacked_replay_round_trips_rows_in_order():
    rep = StackedReplay(2, 5, 3, 2, 2, torch.device("cpu"))
    for t in range(7):
        v = np.array([[t, t, t], [10 + t, 10 + t, 10 + t]], np.float32)
        rep.add(
            v,
            v[:, :2],
            v[:, :2] * 2,
            v + 1,
            np.array([t == 6, False]),
            np.array([False, t == 3]),
            np.array([0, t]),
            np.array([t, 0]),
        )
    assert rep.size == 5 and rep.ptr == 2
    data = rep.chronological(1)
    assert data["obs"][:, 0].tolist() == [12, 13, 14, 15, 16]  # the last 5 rows, oldest first
    assert data["truncated"].tolist() == [False, True, False, False, False]
    assert data["episode"].tolist() == [2, 3, 4, 5, 6]
    assert rep.chronological(0)["terminated"].tolist() == [False, False, False, False, True]
    batch = rep.gather(torch.tensor([[0, 1], [4, 2]]))
    assert batch.obs.shape == (2, 2, 3) and batch.terminated.shape == (2, 2)
    assert batch.obs[1, :, 0].tolist() == [14, 12] and batch.next_obs[1, 0, 0] == 15
    assert batch.reward[0, :, 0].tolist() == [10, 12]  # rows 0, 1 of specialist 0 hold t = 5, 6
    assert batch.terminated[0].tolist() == [0.0, 1.0]


def test_stacked_networks_round_trip():
    torch.manual_seed(0)
    from pipeline.core.nets import Actor

    actors = [Actor(5, 3, [8, 4], [-1, -2, 0], [1, 2, 3]) for _ in range(3)]
    st = StackedActor(actors)
    obs = torch.randn(3, 7, 5)
    out = st(obs)
    for s, a in enumerate(actors):
        torch.testing.assert_close(out[s], a(obs[s]))
        for x, y in zip(st.unstack(s).state_dict().values(), a.state_dict().values()):
            assert torch.equal(x, y)
    ens = [CriticEnsemble(5, 3, [8], 4) for _ in range(3)]
    big = CriticEnsemble.stack(ens)
    act = torch.rand(3, 7, 3)
    q = big.grouped(obs, act)
    for s, e in enumerate(ens):
        torch.testing.assert_close(q[4 * s : 4 * s + 4], e(obs[s], act[s]))
        assert all(torch.equal(x, y) for x, y in zip(big.subset(4 * s, 4 * s + 4).parameters(), e.parameters()))
    picked = big.grouped(obs, act, members=torch.tensor([1, 6, 8]))
    for s, m in enumerate([1, 2, 0]):
        torch.testing.assert_close(picked[s], ens[s].member(obs[s], act[s], m))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_cuda_graphs_match_eager_cuda():
    spec = spec_of()
    jobs = [(0, 0), (0, 1)]
    run = RUN.model_copy(update={"device": "cuda"})
    dev = torch.device("cuda")
    graphed = train_specialists([make_env(ENV, CAP) for _ in jobs], spec, CFG, run, jobs, dev)
    eager = train_specialists(
        [make_env(ENV, CAP) for _ in jobs], spec, CFG.model_copy(update={"cuda_graphs": False}), run, jobs, dev
    )
    for a, b in zip(graphed, eager):
        np.testing.assert_allclose(a.buffer["obs"], b.buffer["obs"], rtol=1e-4, atol=1e-4)
        for x, y in zip(a.actor.parameters(), b.actor.parameters()):
            torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-5)
        for x, y in zip(a.critic.parameters(), b.critic.parameters()):
            torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-5)


# ------------------------------------------------ TD3Learner: the RL agent of PDERL and MOPDERL


def learner_and_reference(spec, cfg, device, primary=1):
    """A TD3Learner and the plain `TD3State` it must equal, from the same initial networks."""
    m = spec.n_objectives
    torch.manual_seed(5)
    actor = Actor(spec.obs_dim, spec.act_dim, cfg.hidden_sizes, spec.action_low, spec.action_high)
    critic = CriticEnsemble(spec.obs_dim, spec.act_dim, cfg.hidden_sizes, 2 * m)
    ref = TD3State(
        actor=copy.deepcopy(actor),
        actor_target=copy.deepcopy(actor).requires_grad_(False),
        critic=copy.deepcopy(critic),
        critic_target=copy.deepcopy(critic).requires_grad_(False),
        actor_opt=None,
        critic_opt=None,
        objectives=list(range(m)),
        primary=primary,
    )
    ref.actor_opt = torch.optim.Adam(ref.actor.parameters(), lr=cfg.actor_lr, fused=True)
    ref.critic_opt = torch.optim.Adam(ref.critic.parameters(), lr=cfg.critic_lr, fused=True)
    state = stack_td3(cfg, [actor], [critic], [list(range(m))], [primary], device)
    learner = TD3Learner(spec, cfg, state, np.random.default_rng(7), noise_seed=11, cuda_rows_seed=13, device=device)
    return learner, ref


def feed(learner, spec, n, seed=0):
    rng = np.random.default_rng(seed)
    for i in range(n):
        learner.add(
            rng.normal(size=spec.obs_dim).astype(np.float32),
            rng.uniform(-1, 1, spec.act_dim).astype(np.float32),
            rng.normal(size=spec.n_objectives),
            rng.normal(size=spec.obs_dim).astype(np.float32),
            bool(i % 17 == 16),
            bool(i % 25 == 24),
            i // 25,
            i % 25,
        )


def test_td3_learner_is_td3_update():
    """PDERL's and MOPDERL's RL agent: its updates are td3_update's on the rows and smoothing
    noise its own streams draw (the stacked path with S = 1; equal up to float rounding)."""
    spec, cfg = spec_of(), CFG
    learner, ref = learner_and_reference(spec, cfg, torch.device("cpu"))
    feed(learner, spec, 60)
    data = learner.buffer.chronological(0)  # not yet wrapped: chronological order is storage order
    learner.train(7)
    rows, noise = np.random.default_rng(7), torch.Generator().manual_seed(11)
    for k in range(1, 8):
        batch = batch_at(data, rows.integers(0, 60, size=cfg.batch_size))
        td3_update(ref, batch, k % cfg.policy_freq == 0, cfg.gamma, cfg.tau, cfg.policy_noise, cfg.noise_clip, noise)
    actor, actor_target, critic, critic_target = learner.networks()
    for mine, theirs in (
        (actor, ref.actor),
        (actor_target, ref.actor_target),
        (critic, ref.critic),
        (critic_target, ref.critic_target),
    ):
        for x, y in zip(mine.parameters(), theirs.parameters()):
            torch.testing.assert_close(x, y, rtol=1e-5, atol=1e-6)
    assert not torch.equal(
        next(actor.parameters()), next(learner_and_reference(spec, cfg, torch.device("cpu"))[1].actor.parameters())
    )
    obs, act = torch.randn(9, spec.obs_dim), torch.rand(9, spec.act_dim)
    torch.testing.assert_close(
        learner.q_primary(obs, act), ref.critic.member(obs, act, 2 * ref.primary), rtol=1e-5, atol=1e-6
    )


def test_stacked_replay_fill_take_latest():
    spec = spec_of()
    buf = StackedReplay(1, 8, spec.obs_dim, spec.act_dim, spec.n_objectives, torch.device("cpu"))
    src = StackedReplay(1, 20, spec.obs_dim, spec.act_dim, spec.n_objectives, torch.device("cpu"))
    rng = np.random.default_rng(1)
    for i in range(11):
        src.add(
            rng.normal(size=(1, spec.obs_dim)),
            rng.uniform(-1, 1, (1, spec.act_dim)),
            rng.normal(size=(1, spec.n_objectives)),
            rng.normal(size=(1, spec.obs_dim)),
            [i == 4],
            [i == 7],
            [i // 5],
            [i % 5],
        )
    data = src.chronological(0)
    buf.fill(data)  # 11 rows into a ring of 8: the latest 8
    assert (buf.size, buf.ptr) == (8, 0)
    got = buf.chronological(0)
    for k, v in data.items():
        assert np.array_equal(got[k], v[3:]), k
    assert np.array_equal(buf.latest(0, 3), data["obs"][-3:])
    assert np.array_equal(buf.latest(0, 3, "episode"), data["episode"][-3:])
    assert np.array_equal(buf.take(0, np.array([6, 1]), "terminated"), data["terminated"][[9, 4]])
    buf.add(data["obs"][:1], data["action"][:1], data["reward"][:1], data["next_obs"][:1], [True], [False], [9], [0])
    assert np.array_equal(buf.latest(0, 2), np.concatenate([data["obs"][-1:], data["obs"][:1]]))  # wraps oldest first


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_td3_learner_on_cuda_graphs_eager_and_resume():
    """On CUDA: the graphed learner matches the eager one, and a learner restored from a
    state_dict mid-run ends where the uninterrupted one does (CUDA: up to float rounding)."""
    spec, dev = spec_of(), torch.device("cuda")
    runs = {}
    for graphs in (True, False):
        learner, _ = learner_and_reference(spec, CFG.model_copy(update={"cuda_graphs": graphs}), dev)
        feed(learner, spec, 60)
        learner.train(30)
        runs[graphs] = learner
    cfg = CFG
    part, _ = learner_and_reference(spec, cfg, dev)
    feed(part, spec, 60)
    part.train(12)
    state = part.state_dict()
    resumed, _ = learner_and_reference(spec, cfg, dev)
    resumed.load_state_dict(state)
    resumed.train(18)
    for other in (runs[False], resumed):
        for x, y in zip(runs[True].networks()[0].parameters(), other.networks()[0].parameters()):
            torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-5)
        for x, y in zip(runs[True].networks()[2].parameters(), other.networks()[2].parameters()):
            torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-5)
    assert resumed.updates == runs[True].updates == 30


def test_restored_optimizers_keep_their_own_flags():
    """A state saved under other optimizer flags (say eager, later resumed under CUDA graphs,
    which need capturable=True) keeps the restoring optimizer's flags; only its state is read."""
    spec, cfg = spec_of(), CFG
    learner, _ = learner_and_reference(spec, cfg, torch.device("cpu"))
    feed(learner, spec, 40)
    learner.train(3)
    saved = learner.state_dict()
    for name in ("actor_opt", "critic_opt"):
        for g in saved["nets"][name]["param_groups"]:
            g["fused"] = False  # as if saved by a differently built optimizer
    fresh, _ = learner_and_reference(spec, cfg, torch.device("cpu"))
    fresh.load_state_dict(saved)
    for opt in (fresh.state.actor_opt, fresh.state.critic_opt):
        assert all(g["fused"] is True for g in opt.param_groups)
    step = next(iter(fresh.state.critic_opt.state.values()))["step"]
    assert float(step) == 3 and fresh.updates == 3
