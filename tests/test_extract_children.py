"""Children of one iteration: K = 1 against the pre-batching code (tests/support/reference_child.py),
and the stacked path."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from support import reference_child

from pipeline.core.envs import make_env
from pipeline.core.nets import Actor, CriticEnsemble
from pipeline.core.seeding import derive_seeds
from pipeline.evaluation import episodes as ex_eval
from pipeline.evaluation.episodes import eval_seeds, evaluate_policy
from pipeline.extraction import children as children_mod
from pipeline.extraction import mapex as ex

OBS, ACT = 17, 6  # mo-halfcheetah-v5's dims, so children can be evaluated in the real env
RETURNS = np.array([[100.0, -300.0], [-5.0, -10.0], [60.0, -100.0]])  # 3 policies, all on the front

# Three settings that together reach every branch of the child's training.
CONFIGS = {
    "paper": dict(weight_norm="l2", max_grad_norm=None, recompute="every_step", norm="none"),
    "precursor": dict(weight_norm="l1", max_grad_norm=0.5, recompute="once", norm="zscore"),
    "range": dict(weight_norm="l2", max_grad_norm=0.5, recompute="every_step", norm="objective_range"),
}


def fixture_inputs():
    """Seeded toy inputs: buffers of 700 and 450 rows (so hybrid sizes differ with the weight),
    two critic ensembles (4 members: twin heads x 2 objectives) and three population actors."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(1234)
        critics = [CriticEnsemble(OBS, ACT, [32, 32], 4).eval() for _ in range(2)]
        actors = [Actor(OBS, ACT, [32, 32], [-1.0] * ACT, [1.0] * ACT).eval() for _ in range(3)]
    rng = np.random.default_rng(99)
    buffers = [
        {"obs": rng.normal(size=(n, OBS)).astype(np.float32), "action": rng.uniform(-1, 1, (n, ACT)).astype(np.float32)}
        for n in (700, 450)
    ]
    return buffers, critics, actors


def child_config(config: str, epochs: int = 2) -> ex.ChildConfig:
    c = CONFIGS[config]
    adv = ex.AdvantageConfig(
        epochs=epochs,
        beta=1.0,
        omega_max=20.0,
        lr=1e-3,
        batch_size=64,
        max_grad_norm=c["max_grad_norm"],
        recompute=c["recompute"],
        norm=c["norm"],
    )
    return ex.ChildConfig(
        hidden_sizes=(32, 32),
        child_buffer_size=600,
        weight_norm=c["weight_norm"],
        warmup_steps=25,
        warmup_lr=1e-3,
        warmup_batch_size=64,
        adv=adv,
    )


# ---------------------------------------------------------------- K = 1: bitwise as before batching


@pytest.fixture
def one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def state_equal(a: Actor, b: Actor) -> bool:
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


def reference(cfg: ex.ChildConfig, numpy_seed: int, torch_seed: int):
    """The frozen pre-batching child on fresh fixture inputs: (actor, parents, weight, counts, stats)."""
    buffers, critics, actors = fixture_inputs()
    return reference_child.make_child(
        RETURNS,
        actors,
        buffers,
        critics,
        hidden_sizes=cfg.hidden_sizes,
        child_buffer_size=cfg.child_buffer_size,
        weight_norm=cfg.weight_norm,
        warmup_steps=cfg.warmup_steps,
        warmup_lr=cfg.warmup_lr,
        warmup_batch_size=cfg.warmup_batch_size,
        adv=cfg.adv,
        rng=np.random.default_rng(numpy_seed),
        torch_seed=torch_seed,
    )


@pytest.mark.parametrize("config", sorted(CONFIGS))
def test_one_child_is_bitwise_what_it_was_before_batching(config, one_thread):
    """What the stage runs for K = 1 on a CPU makes, bit for bit, the child that the code from
    before batching (frozen in tests/support/reference_child.py) makes: weights, parents, target weight,
    hybrid counts and omega statistics. Both run in this process, on this CPU's kernels and
    thread count, so the comparison holds on any machine (no recorded digest)."""
    cfg = child_config(config)
    buffers, critics, actors = fixture_inputs()
    [(child, rec)] = children_mod.make_children(
        RETURNS, actors, buffers, critics, cfg, [ex.ChildSeeds(111, 222, 333)], "cpu"
    )
    ref, parents, weight, counts, stats = reference(cfg, 111, 222)
    assert state_equal(child, ref)
    assert rec.parents == parents and rec.counts.tolist() == counts.tolist()
    np.testing.assert_array_equal(rec.weight, weight)
    assert rec.stats == stats and np.isfinite(stats["omega_mean"])
    # and the comparison does see a child trained on other minibatches
    assert not state_equal(child, reference(cfg, 112, 222)[0])


# ---------------------------------------------------------------- K > 1: a stack of children

SEEDS = [ex.ChildSeeds(111, 222, 333), ex.ChildSeeds(7, 8, 9), ex.ChildSeeds(5, 6, 7)]


def uneven_config(config: str) -> ex.ChildConfig:
    """Hybrid buffers of 615 and 900 rows for SEEDS (10 and 15 steps an epoch at batch 64, short
    last batches of 39 and 4 rows) and warm-up batches of 615 and 640: every padding path."""
    c = child_config(config)
    return replace(c, child_buffer_size=900, warmup_batch_size=640)


def max_abs_diff(a: Actor, b: Actor) -> float:
    return max(float((v - b.state_dict()[k]).abs().max()) for k, v in a.state_dict().items())


@pytest.mark.parametrize("config", sorted(CONFIGS))
def test_each_child_of_a_stack_is_the_child_trained_alone(config, one_thread):
    """Children trained together equal the reference `make_child` trained alone with the same
    seeds: same parents, weight and hybrid rows (exactly), same minibatches, and weights equal
    up to float rounding of the batched matmuls (~1e-8 here). A shared step across children
    (e.g. one gradient-norm clip over all) shows up as differences of ~1e-3."""
    buffers, critics, actors = fixture_inputs()
    cfg = uneven_config(config)
    together = children_mod.make_children(RETURNS, actors, buffers, critics, cfg, SEEDS, "cpu")
    alone = [ex.make_child(RETURNS, actors, buffers, critics, cfg, s, "cpu") for s in SEEDS]
    assert sorted({int(rec.counts.sum()) for _, rec in alone}) == [615, 900]  # uneven lengths are covered
    for (child, rec), (ref, ref_rec) in zip(together, alone):
        assert rec.parents == ref_rec.parents and rec.counts.tolist() == ref_rec.counts.tolist()
        np.testing.assert_array_equal(rec.weight, ref_rec.weight)
        assert rec.stats["omega_mean"] == pytest.approx(ref_rec.stats["omega_mean"], rel=1e-5)
        assert rec.stats["omega_clipped"] == pytest.approx(ref_rec.stats["omega_clipped"], abs=1e-9)
        assert max_abs_diff(child, ref) < 1e-5
    # siblings with the same parents are still different children (own hybrid rows and init)
    assert together[1][1].parents == together[2][1].parents
    assert max_abs_diff(together[1][0], together[2][0]) > 1e-2


def test_make_children_with_one_seed_on_cpu_is_make_child():
    buffers, critics, actors = fixture_inputs()
    cfg = child_config("paper")
    [(child, _)] = children_mod.make_children(RETURNS, actors, buffers, critics, cfg, SEEDS[:1], "cpu")
    ref, _ = ex.make_child(RETURNS, actors, buffers, critics, cfg, SEEDS[0], "cpu")
    assert max_abs_diff(child, ref) == 0.0


class QuadraticCritic(torch.nn.Module):
    """Test critic: Q_m(s, a) = -c * ||a - target_m||^2 for each objective m (both heads equal)."""

    def __init__(self, targets, c=1.0):
        super().__init__()
        self.targets = torch.as_tensor(targets, dtype=torch.float32)  # (m, act_dim)
        self.c = c
        self.n_members = 2 * len(targets)

    def twin_min(self, obs, action):
        return -self.c * ((action[None, :, :] - self.targets[:, None, :]) ** 2).sum(-1)


@pytest.mark.parametrize("norm", ["none", "zscore"])
def test_stacked_rows_are_weighted_by_their_own_advantage_and_come_from_their_own_buffer(monkeypatch, norm):
    """In every stacked step, each real row of child j is a row of child j's own hybrid buffer,
    its action is that row's buffer action, its omega is computed from that same row's (s, a)
    with the critics of its origin buffer, and over the epochs each child sees its own hybrid
    rows exactly `epochs` times."""
    rng = np.random.default_rng(3)
    buffers = []
    for k, n in enumerate((300, 200)):
        obs = np.zeros((n, 3), np.float32)
        obs[:, 0], obs[:, 1], obs[:, 2] = k, np.arange(n), rng.normal(size=n)  # a row names its buffer and index
        buffers.append({"obs": obs, "action": rng.uniform(-1, 1, (n, 2)).astype(np.float32)})
    critics = [QuadraticCritic([[0.8, 0.0], [-0.8, 0.0]]), QuadraticCritic([[0.0, 0.8], [0.0, -0.8]])]
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        actors = [Actor(3, 2, [8], [-1, -1], [1, 1]) for _ in range(3)]
    starts, seen = [], []
    start_child = ex.start_child

    def spy_start(*args, **kwargs):
        starts.append(start_child(*args, **kwargs))
        return starts[-1]

    def spy_step(actor, opt, obs, target, mask, weight=None, max_grad_norm=None, pred=None):
        seen.append((obs.clone(), target.clone(), mask.clone(), weight.clone(), pred.detach().clone()))
        return torch.zeros(len(obs))

    monkeypatch.setattr(children_mod, "start_child", spy_start)  # the name make_children calls
    monkeypatch.setattr(children_mod, "stacked_regression_step", spy_step)
    adv = ex.AdvantageConfig(
        epochs=2, beta=0.5, omega_max=1e6, lr=1e-3, batch_size=64, max_grad_norm=None, recompute="every_step", norm=norm
    )
    cfg = ex.ChildConfig(
        hidden_sizes=(8,),
        child_buffer_size=400,
        weight_norm="l2",
        warmup_steps=0,
        warmup_lr=1e-3,
        warmup_batch_size=64,
        adv=adv,
    )
    children_mod.make_children(RETURNS, actors, buffers, critics, cfg, SEEDS, "cpu")
    weights = torch.tensor(np.stack([s.weight for s in starts]), dtype=torch.float32)
    for j, start in enumerate(starts):
        rows = []
        for obs, act, mask, omega, pi in seen:
            real = mask[j] > 0
            if not real.any():
                continue  # a step past the end of child j's schedule
            o, a, w, p = obs[j][real], act[j][real], omega[j][real], pi[j][real]
            origin, index = o[:, 0].long(), o[:, 1].long()
            for k in (0, 1):
                sel = origin == k
                np.testing.assert_array_equal(a[sel].numpy(), buffers[k]["action"][index[sel].numpy()])
            q_sa = torch.stack(
                [critics[int(k)].twin_min(o[i : i + 1], a[i : i + 1])[:, 0] for i, k in enumerate(origin)]
            )
            q_pi = torch.stack(
                [critics[int(k)].twin_min(o[i : i + 1], p[i : i + 1])[:, 0] for i, k in enumerate(origin)]
            )
            expected = ex.mixed_advantage(q_sa, q_pi, weights[j], norm)
            np.testing.assert_allclose(w.numpy(), torch.exp(expected / 0.5).numpy(), rtol=1e-4, atol=1e-6)
            rows += list(zip(origin.tolist(), index.tolist()))
        own = list(zip(start.hybrid.origin.tolist(), start.hybrid.index.tolist()))
        assert sorted(rows) == sorted(own * 2)  # 2 epochs over its own hybrid buffer, nothing else


def test_clip_per_child_is_torch_clip_on_each_child_alone():
    torch.manual_seed(0)
    stacked = [torch.nn.Parameter(torch.zeros(3, 4, 5)), torch.nn.Parameter(torch.zeros(3, 1, 5))]
    size = torch.tensor([0.01, 1.0, 10.0]).view(3, 1, 1)  # gradient scale of each child
    stacked[0].grad = torch.randn(3, 4, 5) * size
    stacked[1].grad = torch.randn(3, 1, 5) * size
    alone = [[torch.nn.Parameter(torch.zeros_like(p[j])) for p in stacked] for j in range(3)]
    for j, params in enumerate(alone):
        for p, s in zip(params, stacked):
            p.grad = s.grad[j].clone()
    norms = children_mod.clip_grad_norm_per_child_(stacked, 1.0)
    for j, params in enumerate(alone):
        norm = torch.nn.utils.clip_grad_norm_(params, 1.0)
        assert float(norms[j]) == pytest.approx(float(norm), rel=1e-6)
        for p, s in zip(params, stacked):
            torch.testing.assert_close(s.grad[j], p.grad, rtol=1e-6, atol=1e-7)
    assert float(norms[0]) < 1.0 < float(norms[2])  # one child under the clip, one over it


def test_schedules_host_rows_are_make_childs_draws_and_device_rows_are_permutations():
    n, b = 150, 64
    idx, mask = children_mod.epoch_schedule(n, 2, b, np.random.default_rng(5))
    rng = np.random.default_rng(5)
    for e in range(2):
        perm = rng.permutation(n)  # what advantage_weighted_regression draws for epoch e
        np.testing.assert_array_equal(idx[3 * e : 3 * e + 3].flatten()[:n].numpy(), perm)
    assert mask.shape == (6, b) and mask.sum(dim=1).tolist() == [64, 64, 22] * 2
    gen = torch.Generator().manual_seed(1)
    idx_d, mask_d = children_mod.epoch_schedule(n, 2, b, None, gen)
    for e in range(2):
        rows = idx_d[3 * e : 3 * e + 3][mask_d[3 * e : 3 * e + 3] > 0]
        assert sorted(rows.tolist()) == list(range(n))
    again, _ = children_mod.epoch_schedule(n, 2, b, None, torch.Generator().manual_seed(1))
    assert torch.equal(idx_d, again)
    warm = children_mod.warmup_schedule(40, 7, 64, None, torch.Generator().manual_seed(2))
    assert warm.shape == (7, 40) and int(warm.min()) >= 0 and int(warm.max()) < 40
    rng = np.random.default_rng(9)
    host = children_mod.warmup_schedule(500, 3, 64, np.random.default_rng(9))
    np.testing.assert_array_equal(host.numpy(), np.stack([rng.integers(0, 500, size=64) for _ in range(3)]))


def test_stacked_schedule_is_each_childs_own_with_a_bool_mask():
    """stack_schedules keeps every child's rows and real-row mask (as bool, a quarter of float's
    memory), padding past each one's steps and batch; step_slice gives a step's int64 rows and
    float mask."""
    a, ma = children_mod.epoch_schedule(150, 2, 64, np.random.default_rng(5))  # 6 steps of 64 (22 real last)
    b, mb = children_mod.epoch_schedule(70, 1, 32, np.random.default_rng(6))  # 3 steps of 32 (6 real last)
    rows, mask = children_mod.stack_schedules([a, b], [ma, mb])
    assert rows.dtype == torch.int32 and mask.dtype == torch.bool and rows.shape == mask.shape == (6, 2, 64)
    for t in range(6):
        idx, real = children_mod.step_slice(rows, mask, t)
        assert idx.dtype == torch.int64 and real.dtype == torch.float32
        assert torch.equal(idx[0], a[t]) and torch.equal(real[0], ma[t])
        if t < 3:
            assert torch.equal(idx[1, :32], b[t]) and torch.equal(real[1, :32], mb[t])
        assert not real[1, 32:].any() and (t < 3 or not real[1].any())


def test_gather_rows_is_torch_gather_bit_for_bit():
    """The step reads rows by one index_select over the flattened (K * N) rows: the same values
    as torch.gather along each child's own rows, in every dtype the stacked path gathers."""
    torch.manual_seed(0)
    idx = torch.randint(0, 40, (5, 9))
    for x in (torch.randn(5, 40, 7), torch.randn(5, 40, 2).bfloat16(), torch.randint(0, 3, (5, 40, 1))):
        expected = torch.gather(x, 1, idx.unsqueeze(-1).expand(-1, -1, x.shape[-1]))
        got = children_mod.gather_rows(x, idx)
        assert got.dtype == x.dtype and torch.equal(got, expected)
    flat = torch.randn(5, 40)
    assert torch.equal(children_mod.gather_rows(flat, idx), torch.gather(flat, 1, idx))


@pytest.mark.parametrize("k", [8, 16])
def test_wide_stacks_train_each_child_as_it_would_train_alone(k, one_thread):
    """K = 8 and 16 children in one stack (gradient clipping on, uneven hybrid buffers): every
    child equals the reference `make_child` with its seeds up to the float rounding of the
    batched matmuls, so a wider stack changes no child's algorithm."""
    buffers, critics, actors = fixture_inputs()
    cfg = uneven_config("range")
    seeds = [ex.ChildSeeds(*derive_seeds(3, c, n=3)) for c in range(k)]
    together = children_mod.make_children(RETURNS, actors, buffers, critics, cfg, seeds, "cpu")
    assert len(together) == k
    for (child, rec), s in zip(together, seeds):
        ref, ref_rec = ex.make_child(RETURNS, actors, buffers, critics, cfg, s, "cpu")
        assert rec.parents == ref_rec.parents and rec.counts.tolist() == ref_rec.counts.tolist()
        assert max_abs_diff(child, ref) < 1e-5


def test_device_rows_and_gather_paths_run_on_cpu_reproducibly():
    """The CUDA code path (rows drawn from each child's torch generator, critic lookup by
    gather), forced on a CPU: reproducible bit for bit, and different minibatches than the
    host draws (so the children differ, but not by much: same data, same init)."""
    buffers, critics, actors = fixture_inputs()
    cfg = uneven_config("precursor")

    def run():
        return children_mod.make_children(
            RETURNS, actors, buffers, critics, cfg, SEEDS[:2], "cpu", device_rows=True, gather=True
        )

    a, b = run(), run()
    host = children_mod.make_children(RETURNS, actors, buffers, critics, cfg, SEEDS[:2], "cpu")
    for (ca, ra), (cb, _), (ch, rh) in zip(a, b, host):
        assert max_abs_diff(ca, cb) == 0.0
        assert ra.parents == rh.parents and ra.counts.tolist() == rh.counts.tolist()
        assert 0 < max_abs_diff(ca, ch) < 1.0
        assert np.isfinite(ra.stats["omega_mean"])


def test_critic_values_gather_branch_equals_per_origin_branch():
    buffers, critics, _ = fixture_inputs()
    rng = np.random.default_rng(0)
    h = ex.build_hybrid(buffers, np.array([0.6, 0.8]), 500, rng, "cpu")
    per_origin = ex.critic_values(critics, h.obs, h.action, h.origin, gather=False)
    gathered = ex.critic_values(critics, h.obs, h.action, h.origin, gather=True)
    chunked = ex.critic_values(critics, h.obs, h.action, h.origin, chunk=64, gather=True)
    torch.testing.assert_close(gathered, per_origin, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(chunked, per_origin, rtol=1e-6, atol=1e-6)
    # and it is each row's own origin's critic, not the other's
    other = ex.critic_values(critics, h.obs, h.action, 1 - h.origin, gather=False)
    assert (gathered - other).abs().max() > 1e-3


def test_masked_zscore_is_each_childs_zscore_over_its_real_rows():
    torch.manual_seed(0)
    q_sa, q_pi = torch.randn(2, 6, 2), torch.randn(2, 6, 2)
    w = torch.tensor([[0.6, 0.8], [1.0, 0.0]])
    mask = torch.tensor([[1.0] * 6, [1.0] * 4 + [0.0] * 2])
    out = ex.mixed_advantage(q_sa, q_pi, w, "zscore", mask=mask)
    for j, n in enumerate((6, 4)):
        ref = ex.mixed_advantage(q_sa[j, :n], q_pi[j, :n], w[j], "zscore")
        torch.testing.assert_close(out[j, :n], ref, rtol=1e-5, atol=1e-5)


# ---------------------------------------------------------------- evaluation of several children


def test_evaluating_children_together_keeps_each_ones_episodes():
    """Two children evaluated in one loop (one batched forward per step) score what each scores
    alone on its own seeds (up to the batched forward's float rounding), in either order."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(3)
        a, b = (Actor(OBS, ACT, [32, 32], [-1.0] * ACT, [1.0] * ACT).eval() for _ in range(2))
    envs = [make_env("mo-halfcheetah-v5", 30) for _ in range(4)]
    sa, sb = eval_seeds(0, 0, 5, 2), eval_seeds(0, 0, 6, 2)
    together = ex_eval.evaluate_policies([a, b], envs, [sa, sb])
    swapped = ex_eval.evaluate_policies([b, a], envs, [sb, sa])
    for res, actor, seeds, other in ((together[0], a, sa, swapped[1]), (together[1], b, sb, swapped[0])):
        alone = evaluate_policy(actor, envs[:2], seeds)
        np.testing.assert_allclose(res.returns, alone.returns, rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(other.returns, alone.returns, rtol=1e-4, atol=1e-4)
        assert res.env_samples == alone.env_samples == 60
    assert not np.allclose(together[0].returns, together[1].returns)  # different policies were evaluated


# ---------------------------------------------------------------- CUDA (skipped without a GPU)

cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


def _on_cuda(critics, actors):
    return [c.to("cuda") for c in critics], [a.to("cuda") for a in actors]


@cuda
def test_cuda_children_are_reproducible_and_close_to_the_cpu_path():
    buffers, critics, actors = fixture_inputs()
    critics, actors = _on_cuda(critics, actors)
    cfg = uneven_config("precursor")
    a = children_mod.make_children(RETURNS, actors, buffers, critics, cfg, SEEDS[:2], "cuda")
    b = children_mod.make_children(RETURNS, actors, buffers, critics, cfg, SEEDS[:2], "cuda")
    cpu_actors, cpu_critics = fixture_inputs()[2], fixture_inputs()[1]
    cpu = children_mod.make_children(
        RETURNS, cpu_actors, buffers, cpu_critics, cfg, SEEDS[:2], "cpu", device_rows=True, gather=True
    )
    for (ca, ra), (cb, _), (cc, rc) in zip(a, b, cpu):
        assert next(ca.parameters()).is_cuda
        assert max_abs_diff(ca.cpu(), cb.cpu()) == 0.0
        assert ra.parents == rc.parents and ra.counts.tolist() == rc.counts.tolist()
        # CUDA's generator draws other rows than a CPU generator with the same seed: only
        # the scale of the result is comparable
        assert max_abs_diff(ca.cpu(), cc) < 1.0


@cuda
def test_cuda_step_loops_do_not_synchronise_per_step():
    """Host syncs during a stacked run do not grow with the number of steps: none are per step."""
    import warnings

    buffers, critics, actors = fixture_inputs()
    critics, actors = _on_cuda(critics, actors)

    def syncs(warmup_steps: int, batch_size: int) -> int:
        c = child_config("precursor")
        adv = replace(c.adv, batch_size=batch_size, recompute="every_step")
        cfg = replace(c, child_buffer_size=900, warmup_steps=warmup_steps, warmup_batch_size=64, adv=adv)
        torch.cuda.synchronize()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            torch.cuda.set_sync_debug_mode("warn")
            try:
                children_mod.make_children(RETURNS, actors, buffers, critics, cfg, SEEDS[:2], "cuda")
            finally:
                torch.cuda.set_sync_debug_mode("default")
        return sum("synchroniz" in str(w.message) for w in caught)

    assert syncs(10, 64) == syncs(40, 32)  # 4x the warm-up steps, 2x the AWR steps


@cuda
def test_cuda_critic_lookup_takes_the_gather_branch_and_matches_cpu():
    buffers, critics, _ = fixture_inputs()
    h = ex.build_hybrid(buffers, np.array([0.6, 0.8]), 500, np.random.default_rng(0), "cpu")
    cpu = ex.critic_values(critics, h.obs, h.action, h.origin)
    gpu = ex.critic_values([c.to("cuda") for c in critics], h.obs.cuda(), h.action.cuda(), h.origin.cuda())
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-4, atol=1e-4)
