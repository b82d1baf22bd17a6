"""Networks, the TD3 pieces and the checkpoint formats: hand cases and fast-vs-naive checks."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from torch import nn

from pipeline.core.artifacts import ArtifactError
from pipeline.core.buffer import Batch, batch_at
from pipeline.core.checkpoint import check_matches, load_critics, load_policy, save_critics, save_policy
from pipeline.core.envs import EnvSpec
from pipeline.core.nets import Actor, CriticEnsemble
from pipeline.params.td3 import TD3Params
from pipeline.specialists.td3 import (
    actor_loss,
    covered_objectives,
    critic_loss,
    init_td3,
    polyak_update,
    smoothed_target_action,
    td3_targets,
    td3_update,
)

OBS, ACT = 5, 3


def seeded(seed: int, *shape: int) -> torch.Tensor:
    return torch.randn(*shape, generator=torch.Generator().manual_seed(seed))


def linear_stack(ens: CriticEnsemble, e: int) -> nn.Sequential:
    """Member e of the ensemble rebuilt as a plain nn.Linear/ReLU stack (the naive reference)."""
    layers: list[nn.Module] = []
    n = len(ens.weights)
    for i, (w, b) in enumerate(zip(ens.weights, ens.biases)):
        d_in, d_out = w.shape[1:]
        lin = nn.Linear(d_in, d_out)
        with torch.no_grad():
            lin.weight.copy_(w[e].T)
            lin.bias.copy_(b[e, 0])
        layers.append(lin)
        if i < n - 1:
            layers.append(nn.ReLU())
    return nn.Sequential(*layers)


def constant_critic(values: list[float], hidden=(4,)) -> CriticEnsemble:
    """An ensemble whose member e outputs values[e] for every input."""
    ens = CriticEnsemble(OBS, ACT, list(hidden), len(values))
    with torch.no_grad():
        for p in ens.parameters():
            p.zero_()
        ens.biases[-1][:, 0, 0] = torch.tensor(values)
    return ens


# --- networks -----------------------------------------------------------------------------


@settings(max_examples=25, deadline=None)
@given(
    n_pairs=st.integers(1, 3),
    hidden=st.lists(st.integers(1, 12), min_size=1, max_size=3),
    batch=st.integers(1, 9),
    seed=st.integers(0, 2**16),
)
def test_ensemble_forward_equals_a_loop_of_plain_mlps(n_pairs, hidden, batch, seed):
    torch.manual_seed(seed)
    ens = CriticEnsemble(OBS, ACT, hidden, 2 * n_pairs)
    obs, act = seeded(seed, batch, OBS), seeded(seed + 1, batch, ACT)
    fast = ens(obs, act)
    assert fast.shape == (2 * n_pairs, batch)
    naive = torch.stack([linear_stack(ens, e)(torch.cat([obs, act], 1))[:, 0] for e in range(2 * n_pairs)])
    torch.testing.assert_close(fast, naive, rtol=1e-5, atol=1e-5)
    for e in range(2 * n_pairs):
        torch.testing.assert_close(ens.member(obs, act, e), fast[e], rtol=1e-5, atol=1e-5)


def test_members_are_independent_and_initialised_like_linear():
    torch.manual_seed(0)
    ens = CriticEnsemble(OBS, ACT, [16, 16], 4)
    dims = [OBS + ACT, 16, 16]
    for w, b, d_in in zip(ens.weights, ens.biases, dims):
        bound = 1 / np.sqrt(d_in)
        assert w.abs().max() <= bound and b.abs().max() <= bound
        # Members start from different draws.
        assert not torch.equal(w[0], w[1])


def test_twin_min_by_hand():
    ens = constant_critic([4.0, 6.0, 10.0, -2.0])
    obs, act = seeded(0, 3, OBS), seeded(1, 3, ACT)
    assert ens(obs, act).tolist() == [[4.0] * 3, [6.0] * 3, [10.0] * 3, [-2.0] * 3]
    assert ens.twin_min(obs, act).tolist() == [[4.0] * 3, [-2.0] * 3]


def test_twin_min_pairs_adjacent_members():
    torch.manual_seed(3)
    ens = CriticEnsemble(OBS, ACT, [8], 6)
    obs, act = seeded(0, 7, OBS), seeded(1, 7, ACT)
    q = ens(obs, act)
    expected = torch.stack([torch.minimum(q[2 * j], q[2 * j + 1]) for j in range(3)])
    assert torch.equal(ens.twin_min(obs, act), expected)


def test_actor_maps_into_asymmetric_bounds():
    actor = Actor(OBS, 2, [8], low=[-1.0, 0.0], high=[1.0, 4.0])
    last = actor.net[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.zero_()
    assert actor(seeded(0, 4, OBS)).tolist() == [[0.0, 2.0]] * 4  # the centre
    with torch.no_grad():
        last.bias.copy_(torch.tensor([100.0, -100.0]))
    assert actor(seeded(0, 4, OBS)).tolist() == [[1.0, 0.0]] * 4  # saturated at high / low
    assert actor.scale.tolist() == [1.0, 2.0] and actor.centre.tolist() == [0.0, 2.0]


# --- TD3 pieces ---------------------------------------------------------------------------


def test_td3_targets_by_hand_terminated_and_truncated_rows():
    # Rows: 0 ordinary, 1 terminated, 2 truncated by the time limit (not terminal).
    data = {
        "obs": np.zeros((3, OBS), np.float32),
        "action": np.zeros((3, ACT), np.float32),
        "reward": np.array([[1, 10], [2, 20], [3, 30]], np.float32),
        "next_obs": np.ones((3, OBS), np.float32),
        "terminated": np.array([False, True, False]),
        "truncated": np.array([False, False, True]),
    }
    batch = batch_at(data, np.arange(3))
    target = constant_critic([4.0, 6.0, 10.0, -2.0])  # min per objective: 4 and -2
    y = td3_targets(target, batch.next_obs, torch.zeros(3, ACT), batch.reward, batch.terminated, gamma=0.5)
    # y = r + 0.5 * (1 - terminated) * min_h Q'
    assert y.tolist() == [[3.0, 2.0, 5.0], [9.0, 20.0, 29.0]]


def test_td3_targets_carry_no_gradient():
    target = CriticEnsemble(OBS, ACT, [4], 2)
    y = td3_targets(target, seeded(0, 6, OBS), seeded(1, 6, ACT), seeded(2, 6, 1), torch.zeros(6), 0.99)
    assert not y.requires_grad


def test_critic_loss_gives_each_member_its_standalone_mse_gradient():
    torch.manual_seed(0)
    ens = CriticEnsemble(OBS, ACT, [8, 8], 4)
    obs, act = seeded(0, 16, OBS), seeded(1, 16, ACT)
    targets = seeded(2, 2, 16)  # (n_obj, B)
    loss = critic_loss(ens, obs, act, targets)
    loss.backward()
    total = 0.0
    for e in range(4):
        ws = [w[e].detach().clone().requires_grad_() for w in ens.weights]
        bs = [b[e].detach().clone().requires_grad_() for b in ens.biases]
        h = torch.cat([obs, act], 1)
        for i, (w, b) in enumerate(zip(ws, bs)):
            h = h @ w + b
            if i < len(ws) - 1:
                h = torch.relu(h)
        mse = ((h[:, 0] - targets[e // 2]) ** 2).mean()
        mse.backward()
        total += mse.item()
        for i in range(len(ws)):
            torch.testing.assert_close(ens.weights[i].grad[e], ws[i].grad, rtol=1e-5, atol=1e-6)
            torch.testing.assert_close(ens.biases[i].grad[e], bs[i].grad, rtol=1e-5, atol=1e-6)
    assert loss.item() == pytest.approx(total, rel=1e-5)


def test_polyak_update_by_hand():
    online, target = nn.Linear(2, 2), nn.Linear(2, 2)
    with torch.no_grad():
        for p in online.parameters():
            p.fill_(1.0)
        for p in target.parameters():
            p.fill_(0.0)
    polyak_update(online, target, 0.25)
    assert target.weight.tolist() == [[0.25, 0.25]] * 2 and target.bias.tolist() == [0.25, 0.25]
    polyak_update(online, target, 0.25)
    assert target.weight.tolist() == [[0.4375, 0.4375]] * 2  # 0.25 + 0.25 * (1 - 0.25)
    assert online.weight.tolist() == [[1.0, 1.0]] * 2


@given(tau=st.floats(0.001, 1.0), seed=st.integers(0, 1000))
@settings(max_examples=30, deadline=None)
def test_polyak_update_is_a_convex_combination(tau, seed):
    torch.manual_seed(seed)
    online, target = CriticEnsemble(OBS, ACT, [4], 2), CriticEnsemble(OBS, ACT, [4], 2)
    before = [p.detach().clone() for p in target.parameters()]
    polyak_update(online, target, tau)
    for b, o, t in zip(before, online.parameters(), target.parameters()):
        torch.testing.assert_close(t, (1 - tau) * b + tau * o.detach())


@given(seed=st.integers(0, 1000), policy_noise=st.floats(0.0, 50.0), noise_clip=st.floats(0.0, 1.0))
@settings(max_examples=30, deadline=None)
def test_smoothed_target_action_is_clipped_and_in_bounds(seed, policy_noise, noise_clip):
    torch.manual_seed(seed)
    actor = Actor(OBS, 2, [8], low=[-1.0, 0.0], high=[1.0, 4.0])
    next_obs = seeded(seed, 32, OBS)
    a = smoothed_target_action(actor, next_obs, policy_noise, noise_clip, torch.Generator().manual_seed(seed))
    low, high = torch.tensor([-1.0, 0.0]), torch.tensor([1.0, 4.0])
    assert (a >= low).all() and (a <= high).all()
    deviation = (a - actor(next_obs)).abs()
    assert (deviation <= noise_clip * actor.scale + 1e-5).all()


def spec(n_objectives: int = 2) -> EnvSpec:
    return EnvSpec("mo-test-v0", OBS, ACT, n_objectives, (-1.0,) * ACT, (1.0,) * ACT, 100)


CFG = TD3Params(hidden_sizes=[16, 16], batch_size=8, learning_starts=8)


def random_batch(seed: int, n: int = 8, n_objectives: int = 2) -> Batch:
    g = torch.Generator().manual_seed(seed)
    return Batch(
        obs=torch.randn(n, OBS, generator=g),
        action=torch.rand(n, ACT, generator=g) * 2 - 1,
        reward=torch.randn(n, n_objectives, generator=g),
        next_obs=torch.randn(n, OBS, generator=g),
        terminated=(torch.rand(n, generator=g) < 0.3).float(),
    )


def test_covered_objectives():
    assert covered_objectives(1, 3, secondary=True) == ([0, 1, 2], 1)
    assert covered_objectives(1, 3, secondary=False) == ([1], 0)


def test_init_td3_targets_start_equal_and_frozen():
    torch.manual_seed(0)
    state = init_td3(spec(3), CFG, objective=2, device=torch.device("cpu"))
    assert state.critic.n_members == 6 and state.objectives == [0, 1, 2] and state.primary == 2
    for a, b in zip(state.critic.parameters(), state.critic_target.parameters()):
        assert torch.equal(a, b) and not b.requires_grad
    for a, b in zip(state.actor.parameters(), state.actor_target.parameters()):
        assert torch.equal(a, b) and not b.requires_grad
    single = init_td3(spec(3), CFG.model_copy(update={"secondary_critics": False}), 2, torch.device("cpu"))
    assert single.critic.n_members == 2 and single.objectives == [2] and single.primary == 0


def test_actor_step_leaves_every_critic_weight_unchanged():
    torch.manual_seed(0)
    state = init_td3(spec(), CFG, objective=0, device=torch.device("cpu"))
    before = copy.deepcopy(state.critic.state_dict())
    actor_before = copy.deepcopy(state.actor.state_dict())
    loss = actor_loss(state.actor, state.critic, random_batch(0).obs, member=0)
    state.actor_opt.zero_grad()
    loss.backward()
    state.actor_opt.step()
    for k, v in state.critic.state_dict().items():
        assert torch.equal(v, before[k]), k
    assert any(not torch.equal(v, actor_before[k]) for k, v in state.actor.state_dict().items())


def test_actor_gradient_reaches_only_the_chosen_member():
    torch.manual_seed(0)
    ens = CriticEnsemble(OBS, ACT, [8], 4)
    actor = Actor(OBS, ACT, [8], [-1.0] * ACT, [1.0] * ACT)
    actor_loss(actor, ens, seeded(0, 10, OBS), member=2).backward()
    for w in ens.weights:
        assert w.grad[2].abs().sum() > 0
        for e in (0, 1, 3):
            assert torch.count_nonzero(w.grad[e]) == 0


def test_actor_gradient_is_the_same_with_or_without_secondary_critics():
    torch.manual_seed(0)
    alone = CriticEnsemble(OBS, ACT, [8, 8], 2)  # primary objective only
    joint = CriticEnsemble(OBS, ACT, [8, 8], 4)  # objectives [0, 1], primary 1 = members 2, 3
    with torch.no_grad():
        for src, dst in zip(alone.parameters(), joint.parameters()):
            dst[2:4].copy_(src)
    actor = Actor(OBS, ACT, [8], [-1.0] * ACT, [1.0] * ACT)
    obs = seeded(0, 10, OBS)
    grads = []
    for critic, member in ((alone, 0), (joint, 2)):
        actor.zero_grad()
        actor_loss(actor, critic, obs, member).backward()
        grads.append([p.grad.clone() for p in actor.parameters()])
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_secondary_critics_do_not_change_the_primary_update():
    # Specialist for objective 1 with critics for both objectives vs. for objective 1 only,
    # from the same primary weights: actor and primary critic end up the same.
    torch.manual_seed(0)
    joint = init_td3(spec(), CFG, objective=1, device=torch.device("cpu"))
    alone = init_td3(spec(), CFG.model_copy(update={"secondary_critics": False}), 1, torch.device("cpu"))
    with torch.no_grad():
        alone.actor.load_state_dict(joint.actor.state_dict())
        alone.actor_target.load_state_dict(joint.actor_target.state_dict())
        for net in ("critic", "critic_target"):
            for src, dst in zip(getattr(joint, net).parameters(), getattr(alone, net).parameters()):
                dst.copy_(src[2:4])
    for step in range(4):
        batch = random_batch(step)
        for state in (joint, alone):
            td3_update(state, batch, step % 2 == 1, 0.99, 0.005, 0.2, 0.5, torch.Generator().manual_seed(step))
    for a, b in zip(joint.actor.parameters(), alone.actor.parameters()):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    for net in ("critic", "critic_target"):
        for a, b in zip(getattr(joint, net).parameters(), getattr(alone, net).parameters()):
            torch.testing.assert_close(a[2:4], b, rtol=1e-5, atol=1e-6)


def test_td3_update_touches_the_actor_and_targets_only_on_actor_steps():
    torch.manual_seed(0)
    base = init_td3(spec(), CFG, objective=0, device=torch.device("cpu"))
    critic_only, with_actor = copy.deepcopy(base), copy.deepcopy(base)
    batch = random_batch(1)
    m0 = td3_update(critic_only, batch, False, 0.99, 0.005, 0.2, 0.5, torch.Generator().manual_seed(0))
    m1 = td3_update(with_actor, batch, True, 0.99, 0.005, 0.2, 0.5, torch.Generator().manual_seed(0))
    assert set(m0) == {"critic_loss"} and set(m1) == {"critic_loss", "actor_loss"}
    assert torch.equal(m0["critic_loss"], m1["critic_loss"])

    def same(a: nn.Module, b: nn.Module) -> bool:
        return all(torch.equal(x, y) for x, y in zip(a.state_dict().values(), b.state_dict().values()))

    # The online critics get the same step either way; the actor step must not alter them.
    assert same(critic_only.critic, with_actor.critic)
    assert all(p.requires_grad for p in with_actor.critic.parameters())  # trainable again after the actor step
    assert not same(critic_only.critic, base.critic)
    # Without an actor step: actor and both targets untouched.
    for name in ("actor", "actor_target", "critic_target"):
        assert same(getattr(critic_only, name), getattr(base, name)), name
        assert not same(getattr(with_actor, name), getattr(base, name)), name


# --- checkpoints --------------------------------------------------------------------------


META = {
    "env_id": "mo-test-v0",
    "obs_dim": OBS,
    "act_dim": ACT,
    "n_objectives": 2,
    "action_low": [-1.0] * ACT,
    "action_high": [2.0] * ACT,
    "hidden_sizes": [8, 8],
    "seed": 3,
}


def test_policy_round_trip(tmp_path):
    torch.manual_seed(0)
    actor = Actor(OBS, ACT, [8, 8], META["action_low"], META["action_high"])
    target = copy.deepcopy(actor)
    with torch.no_grad():
        target.net[0].weight.add_(1.0)
    save_policy(tmp_path / "policy.pt", actor, META | {"objective": 1}, target)
    loaded, meta = load_policy(tmp_path / "policy.pt")
    assert meta["objective"] == 1 and meta["hidden_sizes"] == [8, 8]
    assert not loaded.training
    obs = seeded(0, 4, OBS)
    assert torch.equal(loaded(obs), actor(obs))
    raw = torch.load(tmp_path / "policy.pt", weights_only=True)
    assert torch.equal(raw["actor_target"]["net.0.weight"], target.net[0].weight)


def test_critics_round_trip_and_member_count(tmp_path):
    torch.manual_seed(0)
    online, target = CriticEnsemble(OBS, ACT, [8, 8], 4), CriticEnsemble(OBS, ACT, [8, 8], 4)
    meta = META | {"buffer_objective": 0, "objectives": [0, 1], "source": "joint"}
    save_critics(tmp_path / "critics.pt", online, target, meta)
    lo, lt, lmeta = load_critics(tmp_path / "critics.pt")
    assert lmeta["objectives"] == [0, 1] and lo.n_members == 4
    obs, act = seeded(0, 4, OBS), seeded(1, 4, ACT)
    assert torch.equal(lo(obs, act), online(obs, act)) and torch.equal(lt(obs, act), target(obs, act))
    with pytest.raises(ValueError, match="two heads per covered objective"):
        save_critics(tmp_path / "bad.pt", online, target, meta | {"objectives": [0]})
    assert not (tmp_path / "bad.pt").exists()


def test_weights_that_contradict_the_metadata_are_an_artifact_error(tmp_path):
    torch.manual_seed(0)
    actor = Actor(OBS, ACT, [8, 8], META["action_low"], META["action_high"])
    save_policy(tmp_path / "policy.pt", actor, META | {"hidden_sizes": [8, 9], "objective": 0})
    with pytest.raises(ArtifactError, match="do not match its metadata"):
        load_policy(tmp_path / "policy.pt")
    with pytest.raises(ArtifactError, match="expected 'mapex.critics'"):
        load_critics(tmp_path / "policy.pt")


def test_check_matches_names_the_disagreeing_key():
    check_matches("a.pt", META, dict(META), "buffer")
    with pytest.raises(ArtifactError, match=r"a.pt: obs_dim = 5 does not match buffer \(obs_dim = 6\)"):
        check_matches("a.pt", META, META | {"obs_dim": 6}, "buffer")


@pytest.mark.parametrize("fused", [True, False], ids=["fused", "plain"])
def test_adam_step_is_bitwise_optimizer_step(fused):
    """adam_step (the stacked update's shortcut past Optimizer.step's bookkeeping) leaves
    parameters and Adam state with the very bits opt.step() does, step after step; a plain
    (unfused) Adam, and the first step (no state yet), go through opt.step() itself."""
    from pipeline.specialists.td3 import adam_step, clear_grads

    torch.manual_seed(0)
    nets = [CriticEnsemble(5, 2, [16, 16], 4) for _ in range(2)]
    nets[1].load_state_dict(nets[0].state_dict())
    opts = [torch.optim.Adam(n.parameters(), lr=3e-4, fused=fused) for n in nets]
    x, a = torch.randn(32, 5), torch.randn(32, 2)
    for step in range(6):
        for i, (net, opt) in enumerate(zip(nets, opts)):
            clear_grads(opt) if i else opt.zero_grad(set_to_none=True)
            (net(x, a) ** 2).mean().backward()
            adam_step(opt) if i else opt.step()
        for p, q in zip(nets[0].parameters(), nets[1].parameters()):
            assert torch.equal(p, q), step
        for p, q in zip(nets[0].parameters(), nets[1].parameters()):
            for key in ("step", "exp_avg", "exp_avg_sq"):
                assert torch.equal(opts[0].state[p][key], opts[1].state[q][key]), (step, key)
    assert all(p.grad is not None for p in nets[1].parameters())
    clear_grads(opts[1])
    assert all(p.grad is None for p in nets[1].parameters())
