"""MAPEX extraction core: gaps, weights, hybrid buffer, mixed advantage, AWR loss, behaviour."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.core.nets import Actor
from pipeline.extraction import mapex as ex

# ---------------------------------------------------------------- gaps and parents


def test_front_edges_sorts_front_and_drops_dominated():
    returns = np.array(
        [
            [0.0, 10.0],  # 0 front
            [10.0, 0.0],  # 1 front
            [5.0, 5.0],  # 2 front
            [4.0, 4.0],  # 3 dominated by 2
            [0.0, 0.0],  # 4 dominated
        ]
    )
    ids, lengths = ex.front_edges(returns)
    assert ids.tolist() == [0, 2, 1]
    # population range is 10 on both objectives: edges (0,1)-(.5,.5) and (.5,.5)-(1,0)
    np.testing.assert_allclose(lengths, [np.sqrt(0.5), np.sqrt(0.5)])


def test_front_edges_normalises_scales():
    # objective 1 is 1000x larger; raw distances would ignore objective 0 entirely
    returns = np.array([[0.0, 1000.0], [1.0, 900.0], [2.0, 0.0]])
    _, lengths = ex.front_edges(returns)
    np.testing.assert_allclose(lengths, [np.hypot(0.5, 0.1), np.hypot(0.5, 0.9)])


def test_front_edges_rejects_three_objectives():
    with pytest.raises(ValueError, match="2 objectives"):
        ex.front_edges(np.zeros((3, 3)))


def test_roulette_frequencies_follow_edge_lengths():
    # front points at x = 0, 1, 4 on the line x + y = 4: normalised edge lengths 1 : 3
    returns = np.array([[0.0, 4.0], [1.0, 3.0], [4.0, 0.0]])
    rng = np.random.default_rng(0)
    draws = [ex.select_parents(returns, rng) for _ in range(4000)]
    share = np.mean([d == (0, 1) for d in draws])
    assert all(d in [(0, 1), (1, 2)] for d in draws)
    assert abs(share - 0.25) < 0.03


def test_single_front_point_falls_back_to_per_objective_best():
    returns = np.array([[5.0, 5.0], [1.0, 4.0], [4.0, 1.0]])
    assert ex.select_parents(returns, np.random.default_rng(0)) == (0, 0)


# ---------------------------------------------------------------- target weights


def test_target_weight_l2_and_l1_hand_cases():
    returns = np.array([[0.0, -4500.0], [100.0, -9000.0], [50.0, -6750.0]])
    # normalised: parent 0 -> (0, 1), parent 1 -> (1, 0): centroid (.5, .5)
    np.testing.assert_allclose(ex.target_weight(returns, [0, 1], "l2"), [2**-0.5, 2**-0.5])
    np.testing.assert_allclose(ex.target_weight(returns, [0, 1], "l1"), [0.5, 0.5])
    # parents (0, 1) and (.5, .5): centroid (.25, .75)
    w = ex.target_weight(returns, [0, 2], "l2")
    np.testing.assert_allclose(w, np.array([0.25, 0.75]) / np.hypot(0.25, 0.75))


@settings(max_examples=50, deadline=None)
@given(
    st.lists(st.tuples(st.floats(-1e4, 1e4), st.floats(-1e4, 1e4)), min_size=2, max_size=12),
    st.data(),
)
def test_target_weight_is_unit_and_non_negative(points, data):
    returns = np.array(points)
    i = data.draw(st.integers(0, len(points) - 1))
    j = data.draw(st.integers(0, len(points) - 1))
    w = ex.target_weight(returns, [i, j], "l2")
    assert np.all(w >= 0)
    assert np.linalg.norm(w) == pytest.approx(1.0)


# ---------------------------------------------------------------- hybrid buffer


def _buffers(sizes, obs_dim=3, act_dim=2):
    out = []
    for k, n in enumerate(sizes):
        idx = np.arange(n, dtype=np.float32)
        # obs[:, 0] = origin, obs[:, 1] = row index: every row identifies itself
        obs = np.stack([np.full(n, k, np.float32), idx] + [np.zeros(n, np.float32)] * (obs_dim - 2), axis=1)
        act = np.full((n, act_dim), 0.5 if k == 0 else -0.5, np.float32)
        out.append({"obs": obs, "action": act})
    return out


def test_hybrid_counts_proportional_and_capped():
    assert ex.hybrid_counts(np.array([0.6, 0.8]), 1000, [10_000, 10_000]).tolist() == [429, 571]
    assert ex.hybrid_counts(np.array([1.0, 0.0]), 1000, [300, 10_000]).tolist() == [300, 0]
    # buffer 0 cannot supply its 571 rows: the hybrid shrinks and keeps the 3 : 4 proportion
    assert ex.hybrid_counts(np.array([0.8, 0.6]), 1000, [400, 10_000]).tolist() == [400, 300]


@settings(max_examples=100, deadline=None)
@given(st.floats(0.0, 1.0), st.integers(10, 5000), st.integers(1, 3000), st.integers(1, 3000))
def test_hybrid_counts_keep_proportions_and_never_overdraw(a, size, n0, n1):
    w = np.array([a, np.sqrt(max(0.0, 1 - a * a))])
    counts = ex.hybrid_counts(w, size, [n0, n1])
    assert counts[0] <= n0 and counts[1] <= n1 and counts.sum() <= size + 1
    share = w / w.sum()
    total = counts.sum()
    assert np.all(np.abs(counts - share * total) <= 1.0 + 1e-9)


def test_build_hybrid_rows_remember_their_origin_without_repeats():
    bufs = _buffers([400, 600])
    h = ex.build_hybrid(bufs, np.array([0.6, 0.8]), 500, np.random.default_rng(1), "cpu")
    origin = h.origin.numpy()
    assert np.bincount(origin).tolist() == [214, 286]
    np.testing.assert_array_equal(h.obs[:, 0].numpy(), origin)  # obs came from the origin buffer
    np.testing.assert_array_equal(h.obs[:, 1].numpy(), h.index)  # and from the recorded row
    for k in (0, 1):
        rows = h.index[origin == k]
        assert len(np.unique(rows)) == len(rows)  # without replacement inside a buffer


# ---------------------------------------------------------------- mixed advantage and weights


class QuadraticCritic(torch.nn.Module):
    """Test critic: Q_m(s, a) = -c * ||a - target_m||^2 for each objective m (both heads equal)."""

    def __init__(self, targets, c=10.0):
        super().__init__()
        self.targets = torch.as_tensor(targets, dtype=torch.float32)  # (m, act_dim)
        self.c = c
        self.n_members = 2 * len(targets)

    def twin_min(self, obs, action):
        return -self.c * ((action[None, :, :] - self.targets[:, None, :]) ** 2).sum(-1)


def test_mixed_advantage_hand_case_and_normalisations():
    q_sa = torch.tensor([[3.0, 10.0], [1.0, -10.0]])
    q_pi = torch.tensor([[1.0, 0.0], [1.0, 0.0]])
    w = torch.tensor([0.5, 0.5])
    np.testing.assert_allclose(ex.mixed_advantage(q_sa, q_pi, w, "none").numpy(), [6.0, -5.0])
    scaled = ex.mixed_advantage(q_sa, q_pi, w, "objective_range", torch.tensor([2.0, 20.0]))
    np.testing.assert_allclose(scaled.numpy(), [0.5 * 1 + 0.5 * 0.5, 0.5 * 0 - 0.5 * 0.5])
    z = ex.mixed_advantage(q_sa, q_pi, w, "zscore")
    np.testing.assert_allclose(z.numpy(), [1.0, -1.0], atol=1e-6)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-1e3, 1e3), min_size=1, max_size=50), st.floats(0.05, 5.0), st.floats(0.5, 50.0))
def test_awr_weight_positive_clipped_and_monotone(adv, beta, omega_max):
    a = torch.tensor(sorted(adv), dtype=torch.float64)
    w = ex.awr_weight(a, beta, omega_max)
    assert torch.all(w >= 0)  # exp underflows to 0 for very negative advantages
    assert torch.all(w <= omega_max * (1 + 1e-9))
    assert torch.all(w[1:] >= w[:-1])
    small = a / beta < np.log(omega_max) - 1e-6
    np.testing.assert_allclose(w[small].numpy(), torch.exp(a[small] / beta).numpy(), rtol=1e-9)


def test_child_configs_are_keyword_only():
    """Four of AdvantageConfig's fields are floats: built by position they could silently swap."""
    fields = dict(epochs=2, beta=0.5, omega_max=20.0, lr=1e-3, batch_size=64, max_grad_norm=None)
    with pytest.raises(TypeError):
        ex.AdvantageConfig(2, 0.5, 20.0, 1e-3, 64, None, "every_step", "none")
    adv = ex.AdvantageConfig(**fields, recompute="every_step", norm="none")
    assert (adv.beta, adv.omega_max, adv.lr) == (0.5, 20.0, 1e-3)
    with pytest.raises(TypeError):
        ex.ChildConfig((8,), 400, "l2", 0, 1e-3, 64, adv)


def test_each_advantage_weights_exactly_its_own_row(monkeypatch):
    """The omega used in every loss term is the one computed from that same row's (s, a)."""
    bufs = _buffers([300, 300])
    rng = np.random.default_rng(3)
    for b in bufs:  # distinct actions per row
        b["action"] = rng.uniform(-1, 1, size=b["action"].shape).astype(np.float32)
    h = ex.build_hybrid(bufs, np.array([0.5, 0.5]), 400, rng, "cpu")
    critics = [QuadraticCritic([[0.8, 0.0], [-0.8, 0.0]], c=1.0), QuadraticCritic([[0.0, 0.8], [0.0, -0.8]], c=1.0)]
    torch.manual_seed(0)
    actor = Actor(3, 2, [16], [-1, -1], [1, 1])
    w = torch.tensor([0.6, 0.8])
    seen = []

    def spy(actor_, opt, obs, target, weight=None, max_grad_norm=None, pred=None):
        assert pred is None or torch.equal(pred.detach(), actor_(obs).detach())
        seen.append((obs.clone(), target.clone(), weight.clone(), actor_(obs).detach().clone()))
        return torch.zeros(())

    monkeypatch.setattr(ex, "regression_step", spy)
    cfg = ex.AdvantageConfig(
        epochs=2,
        beta=0.5,
        omega_max=1e6,
        lr=1e-3,
        batch_size=64,
        max_grad_norm=None,
        recompute="every_step",
        norm="none",
    )
    ex.advantage_weighted_regression(actor, h, critics, w, torch.ones(2), cfg, np.random.default_rng(0))
    assert sum(len(s[0]) for s in seen) == 2 * len(h.obs)
    for obs, act, omega, pi in seen:
        origin = obs[:, 0].long()  # rows identify their buffer in obs[:, 0]
        for i in range(len(obs)):
            c = critics[int(origin[i])]
            adv = c.twin_min(obs[i : i + 1], act[i : i + 1])[:, 0] - c.twin_min(obs[i : i + 1], pi[i : i + 1])[:, 0]
            expected = min(float(torch.exp((adv @ w) / 0.5)), 1e6)
            assert omega[i] == pytest.approx(expected, rel=1e-5)
        # and each action is the buffer action of the row its obs names
        rows = obs[:, 1].long().numpy()
        for k in (0, 1):
            sel = (origin == k).numpy()
            np.testing.assert_array_equal(act[sel].numpy(), bufs[k]["action"][rows[sel]])


# ---------------------------------------------------------------- behaviour on a toy problem


def _toy_child(weight, norm="none", beta=0.2, epochs=30, seed=0):
    """Two buffers over the same states: buffer 0 acts +0.5, buffer 1 acts -0.5. Each buffer's
    critic for objective 0 prefers +0.5 and for objective 1 prefers -0.5."""
    rng = np.random.default_rng(seed)
    n = 512
    states = rng.normal(size=(n, 3)).astype(np.float32)
    bufs = [
        {"obs": states, "action": np.full((n, 1), 0.5, np.float32)},
        {"obs": states, "action": np.full((n, 1), -0.5, np.float32)},
    ]
    critic = QuadraticCritic([[0.5], [-0.5]], c=1.0)
    h = ex.build_hybrid(bufs, np.array([1.0, 1.0]), 512, rng, "cpu")  # fixed 50/50 composition
    torch.manual_seed(seed)
    actor = Actor(3, 1, [32, 32], [-1], [1])
    ex.warm_up(actor, h.obs, torch.zeros(len(h.obs), 1), 200, 3e-3, 128, rng)  # start at the mean action 0
    cfg = ex.AdvantageConfig(
        epochs=epochs,
        beta=beta,
        omega_max=100.0,
        lr=3e-3,
        batch_size=128,
        max_grad_norm=None,
        recompute="every_step",
        norm=norm,
    )
    ex.advantage_weighted_regression(actor, h, [critic, critic], torch.tensor(weight), torch.ones(2), cfg, rng)
    with torch.no_grad():
        return float(actor(torch.as_tensor(states)).mean())


def test_child_moves_from_one_buffers_actions_to_the_others_as_weight_turns():
    actions = [_toy_child(w) for w in ([1.0, 0.0], [2**-0.5, 2**-0.5], [0.0, 1.0])]
    assert actions[0] > 0.3  # objective 0 only: clone buffer 0's +0.5
    assert abs(actions[1]) < 0.15  # balanced: in between
    assert actions[2] < -0.3  # objective 1 only: clone buffer 1's -0.5
    assert actions[0] > actions[1] > actions[2]


def test_warm_up_regresses_onto_mean_parent_action():
    torch.manual_seed(0)
    p1, p2 = Actor(2, 1, [8], [-1], [1]), Actor(2, 1, [8], [-1], [1])
    obs = torch.randn(256, 2)
    target = ex.mean_parent_action([p1, p2], obs)
    np.testing.assert_allclose(target.numpy(), ((p1(obs) + p2(obs)) / 2).detach().numpy(), rtol=1e-6)
    child = Actor(2, 1, [32, 32], [-1], [1])
    before = float(((child(obs) - target) ** 2).mean())
    ex.warm_up(child, obs, target, 300, 3e-3, 64, np.random.default_rng(0))
    after = float(((child(obs) - target) ** 2).mean())
    assert after < 0.1 * before


# ---------------------------------------------------------------- the non-dominated filter


def test_pareto_mask_recovers_a_known_front():
    """Points on the unit quarter circle are mutually non-dominated; each scaled by 0.3..0.95 is
    dominated by its own original."""
    from pipeline.core.pareto import pareto_mask

    rng = np.random.default_rng(0)
    angles = rng.uniform(0, np.pi / 2, 40)
    front = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    dominated = front[:25] * rng.uniform(0.3, 0.95, (25, 1))
    points = np.concatenate([dominated, front])
    order = rng.permutation(len(points))
    mask = pareto_mask(points[order])
    assert mask.sum() == 40
    np.testing.assert_array_equal(np.sort(order[mask]), np.arange(25, 65))


@settings(max_examples=100, deadline=None)
@given(st.lists(st.tuples(st.integers(-20, 20), st.integers(-20, 20)), min_size=1, max_size=30))
def test_pareto_mask_properties(points):
    from pipeline.core.pareto import pareto_mask

    p = np.array(points, dtype=float)
    mask = pareto_mask(p)
    front = p[mask]
    assert pareto_mask(front).all()  # idempotent
    for col in range(2):  # the best point on each objective always survives (one of the ties)
        best = p[:, col].max()
        assert (front[:, col] == best).any()
    for q in p[~mask]:  # every removed point is dominated by some survivor
        assert any((f >= q).all() and (f > q).any() for f in front)
