"""The hybrid extraction (extract.init interpolate, seed_interpolation; not in the paper) and early
stopping (extract.stop_patience): a hybrid child before training is its parents' interpolated
policy, bit for bit; it falls back to the paper's start where they cannot be mixed; seeds are
the interpolation baseline's policies; the stopping rule stops a toy run where it should."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from pipeline.baselines.interpolate import interpolate
from pipeline.core.envs import env_spec, make_env, spec_meta
from pipeline.core.mixing import mix_actors
from pipeline.core.nets import Actor, CriticEnsemble
from pipeline.core.population import Member, load_population, save_population
from pipeline.core.specialist import StartingPolicy
from pipeline.extraction import mapex as ex
from pipeline.extraction.children import make_children
from pipeline.extraction.run import ExtractionRun, child_seeds, should_stop, stop_hypervolume, variant_config
from pipeline.params.extract import EXTENSION_KEYS, WARMUP_ONLY_KEYS, ExtractParams, without_default_extensions

OBS, ACT = 17, 6  # mo-halfcheetah-v5's
ENV, CAP = "mo-halfcheetah-v5", 12
RETURNS = np.array([[100.0, -300.0], [-5.0, -10.0], [60.0, -100.0]])  # 3 policies, all on the front


def inputs(hidden=(32, 32)):
    """Seeded toy buffers (700 and 450 rows), two critic ensembles and three population actors."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(1234)
        critics = [CriticEnsemble(OBS, ACT, [32, 32], 4).eval() for _ in range(2)]
        actors = [Actor(OBS, ACT, list(hidden), [-1.0] * ACT, [1.0] * ACT).eval() for _ in range(3)]
    rng = np.random.default_rng(99)
    buffers = [
        {"obs": rng.normal(size=(n, OBS)).astype(np.float32), "action": rng.uniform(-1, 1, (n, ACT)).astype(np.float32)}
        for n in (700, 450)
    ]
    return buffers, critics, actors


def config(init="interpolate", epochs=2, hidden=(32, 32), warmup_after=False) -> ex.ChildConfig:
    adv = ex.AdvantageConfig(
        epochs=epochs,
        beta=1.0,
        omega_max=20.0,
        lr=1e-3,
        batch_size=64,
        max_grad_norm=None,
        recompute="every_step",
        norm="none",
    )
    return ex.ChildConfig(
        hidden_sizes=hidden,
        child_buffer_size=600,
        weight_norm="l2",
        warmup_steps=25,
        warmup_lr=1e-3,
        warmup_batch_size=64,
        adv=adv,
        init=init,
        warmup_after_interpolate=warmup_after,
    )


def same(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    sa, sb = a.state_dict(), b.state_dict()
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


# ---------------------------------------------------------------- a child's start


def test_a_hybrid_child_before_training_is_its_parents_interpolated_policy_bit_for_bit():
    buffers, _, actors = inputs()
    child = ex.start_child(RETURNS, actors, buffers, config(), np.random.default_rng(5), 77, "cpu")
    assert child.init == "interpolated" and child.fallback is None and child.warmup_steps == 0
    assert len(child.a_bar) == 0  # no warm-up: the mean parent action is not computed
    mixed = mix_actors([actors[p] for p in child.parents], [0.5, 0.5])
    assert same(child.actor, mixed)
    # and it is neither parent: a mix of two different networks
    assert not any(same(child.actor, actors[p]) for p in child.parents)


@pytest.mark.parametrize("stacked", [False, True], ids=["one-child", "stacked"])
def test_without_training_steps_the_child_is_the_interpolated_policy(stacked):
    """epochs 0 and no warm-up: the whole child is its start, on the reference path and stacked
    (masked warm-up steps of zero gradient leave a child untouched)."""
    buffers, _, actors = inputs()
    cfg = config(epochs=0)
    seeds = child_seeds(3, 1, 2 if stacked else 1)
    out = make_children(RETURNS, actors, buffers, None, cfg, seeds, "cpu", stacked=stacked)
    for (actor, rec), s in zip(out, seeds):
        assert rec.init == "interpolated"
        assert same(actor, mix_actors([actors[p] for p in rec.parents], [1 / len(rec.parents)] * len(rec.parents)))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (benchmarks/device/check.sh runs it there)")
def test_cuda_stacked_children_without_training_steps_are_the_interpolated_policy():
    """The CUDA path (fused Adam, rows drawn on the device): masked warm-up steps of zero gradient
    leave an interpolated child exactly at its start there too."""
    buffers, _, actors = inputs()
    cuda = [a.to("cuda") for a in actors]
    out = make_children(RETURNS, cuda, buffers, None, config(epochs=0), child_seeds(3, 1, 2), "cuda")
    for actor, rec in out:
        mixed = mix_actors([actors[p] for p in rec.parents], [1 / len(rec.parents)] * len(rec.parents))
        assert same(actor.cpu(), mixed)


def test_warmup_after_interpolate_warms_up_from_the_interpolated_start():
    buffers, _, actors = inputs()
    start = ex.start_child(RETURNS, actors, buffers, config(warmup_after=True), np.random.default_rng(5), 77, "cpu")
    assert start.warmup_steps == 25 and start.a_bar.shape == (len(start.hybrid.obs), ACT)
    assert same(start.actor, mix_actors([actors[p] for p in start.parents], [0.5, 0.5]))
    (trained, _), *_ = make_children(
        RETURNS, actors, buffers, None, config(epochs=0, warmup_after=True), [child_seeds(3, 1, 1)[0]], "cpu"
    )
    (untrained, _), *_ = make_children(
        RETURNS, actors, buffers, None, config(epochs=0), [child_seeds(3, 1, 1)[0]], "cpu"
    )
    assert not same(trained, untrained)  # the warm-up moved it


def test_parents_of_another_architecture_fall_back_to_the_papers_start():
    """Parents 32-32, children 16-16: the child starts as the paper's (same draws, same weights)
    and its record says why."""
    buffers, _, actors = inputs()
    hybrid = ex.start_child(RETURNS, actors, buffers, config(hidden=(16, 16)), np.random.default_rng(5), 77, "cpu")
    paper = ex.start_child(
        RETURNS, actors, buffers, config("warmup", hidden=(16, 16)), np.random.default_rng(5), 77, "cpu"
    )
    assert hybrid.init == "warmup" and "hidden sizes [32, 32]" in hybrid.fallback
    assert paper.init is None and paper.fallback is None
    assert hybrid.warmup_steps == paper.warmup_steps == 25
    assert same(hybrid.actor, paper.actor) and torch.equal(hybrid.a_bar, paper.a_bar)
    seeds = [child_seeds(3, 1, 1)[0]]
    (a, rec), *_ = make_children(RETURNS, actors, buffers, None, config(epochs=0, hidden=(16, 16)), seeds, "cpu")
    (b, _), *_ = make_children(
        RETURNS, actors, buffers, None, config("warmup", epochs=0, hidden=(16, 16)), seeds, "cpu"
    )
    assert rec.init == "warmup" and rec.fallback and same(a, b)


def test_interpolation_problem_names_what_differs():
    _, _, actors = inputs()
    assert ex.interpolation_problem(actors[:2], (32, 32)) is None
    assert "hidden sizes" in ex.interpolation_problem(actors[:2], (64, 64))
    other = Actor(OBS, ACT, [32, 32], [-2.0] * ACT, [2.0] * ACT)
    assert "action bounds" in ex.interpolation_problem([actors[0], other], (32, 32))


# ---------------------------------------------------------------- params


def test_extension_keys_default_to_the_paper_and_are_recorded_only_where_set():
    cfg = ExtractParams()
    assert (cfg.init, cfg.seed_interpolation, cfg.stop_patience) == ("warmup", 0, 0)
    dump = cfg.model_dump()
    assert not set(EXTENSION_KEYS) & set(without_default_extensions(dump))
    assert not set(EXTENSION_KEYS) & set(WARMUP_ONLY_KEYS)
    hybrid = without_default_extensions(cfg.model_copy(update={"init": "interpolate", "stop_patience": 3}).model_dump())
    assert hybrid["init"] == "interpolate" and hybrid["stop_patience"] == 3 and hybrid["stop_min_gain"] == 0.01
    assert hybrid["warmup_after_interpolate"] is False and "seed_interpolation" not in hybrid
    # the warm-up-only ablation is the paper's, whatever the extensions say
    ablation = variant_config(cfg.model_copy(update={"init": "interpolate", "epochs": 5}), "warmup_only")
    assert ablation.init == "warmup" and ablation.epochs == 0
    with pytest.raises(ValueError):
        ExtractParams(init="mix")


def test_a_population_without_init_keeps_its_bytes_and_one_with_it_loads(tmp_path):
    m = Member("child", None, 1, [0, 1], [0.6, 0.8], [1.0, 2.0], [0.0, 0.0], 2, 10, [4], {"w": torch.zeros(1)})
    save_population(tmp_path / "a.pt", [m], {"n_objectives": 2})
    raw = torch.load(tmp_path / "a.pt", weights_only=True)
    assert "init" not in raw["members"][0]
    save_population(tmp_path / "b.pt", [replace(m, init="interpolated")], {"n_objectives": 2})
    (loaded,), _ = load_population(tmp_path / "b.pt")
    assert loaded.init == "interpolated"


# ---------------------------------------------------------------- early stopping: the rule


def test_stopping_rule_on_hand_curves():
    curve = [0.0, 1.0, 1.5, 1.505, 1.51]
    assert not should_stop(curve[:2], 2, 0.01)  # t = 1 < patience
    assert not should_stop(curve[:3], 2, 0.01)  # 1.5 - 0 > 0
    assert not should_stop(curve[:4], 2, 0.01)  # 1.505 - 1.0 = 0.505 > 0.01
    assert should_stop(curve[:5], 2, 0.01)  # 1.51 - 1.5 = 0.01 <= 0.01 * 1.5
    assert not should_stop(curve[:5], 2, 0.001)  # 0.01 > 0.0015
    assert not should_stop(curve, 0, 0.5)  # patience 0: off
    assert should_stop([0.0, 0.0], 1, 0.0)  # nothing ever entered the box: stops too


def test_stop_hypervolume_is_in_units_of_the_starting_policies():
    lo, span = np.array([0.0, 0.0]), np.array([2.0, 4.0])
    assert stop_hypervolume(np.array([[2.0, 0.0], [0.0, 4.0]]), lo, span) == 0.0  # the specialists alone
    assert stop_hypervolume(np.array([[1.0, 2.0]]), lo, span) == pytest.approx(0.25)
    assert stop_hypervolume(np.array([[1.0, 2.0], [-1.0, 8.0]]), lo, span) == pytest.approx(0.25)  # below lo: nothing


# ---------------------------------------------------------------- tiny runs


@pytest.fixture(scope="module")
def envs():
    made = [make_env(ENV, CAP) for _ in range(2)]
    yield made
    for env in made:
        env.close()


def tiny_run(envs, **extract) -> ExtractionRun:
    buffers, critics, actors = inputs()
    starts = [StartingPolicy(0, "policy", actors[0], [32, 32]), StartingPolicy(1, "policy", actors[1], [32, 32])]
    settings = dict(
        iterations=6,
        child_buffer_size=300,
        eval_episodes=2,
        warmup_steps=10,
        warmup_batch_size=64,
        epochs=1,
        beta=1.0,
        omega_max=20.0,
        batch_size=64,
        hidden_sizes=[32, 32],
        device="cpu",
    )
    cfg = ExtractParams(**(settings | extract))
    meta = spec_meta(env_spec(envs[0], ENV, CAP))
    return ExtractionRun(starts, buffers, critics, cfg, meta, 3, envs, torch.device("cpu"))


def run(r: ExtractionRun) -> ExtractionRun:
    r.start()
    while not r.done:
        r.step()
    return r


def test_seeds_are_the_interpolation_baselines_policies_and_children_draw_from_them(envs):
    r = run(tiny_run(envs, iterations=2, seed_interpolation=3, init="interpolate"))
    assert [m.origin for m in r.members] == ["specialist"] * 2 + ["interpolated"] * 3 + ["child"] * 2
    assert [m.iteration for m in r.members] == [0] * 5 + [1, 2]
    baseline = interpolate(r.starts, 2, policies=3, per_iteration=1, eval_episodes=2, seed=3, envs=envs)
    for mine, theirs in zip(r.members[:5], baseline):
        assert mine.returns == theirs.returns and mine.target_weight == theirs.target_weight
        assert all(torch.equal(mine.actor[k], v) for k, v in theirs.actor.items())
    assert [m.init for m in r.members[5:]] == ["interpolated"] * 2
    assert r.record() == {"init_fallbacks": {}, "seed_interpolation": {"policies": 3, "problem": None}}
    assert [c["phase"] for c in r.costs] == ["start", "seeds", "children", "children"]
    assert r.costs[1]["policies"] == 3 and all(c["eval_cpu_s"] >= 0 for c in r.costs)
    # resumable: the state carries the seeds, costs and fallbacks
    again = tiny_run(envs, iterations=2, seed_interpolation=3, init="interpolate")
    again.load_state_dict(r.state_dict())
    assert again.iteration == 2 and again.done and again.costs == r.costs


def test_early_stopping_stops_a_toy_run_where_the_rule_says(envs):
    """The rule applied to the run's own curve: it stops at the first iteration where the
    hypervolume has not risen by the fraction over the patience, and not before."""
    full = run(tiny_run(envs, iterations=8))
    assert full.iteration == 8 and full.stopped_at is None and full.record() == {}
    # the curve of the full run, computed as the rule computes it
    returns = np.array([m.returns for m in full.members])
    lo, hi = returns[:2].min(axis=0), returns[:2].max(axis=0)
    span = np.where(hi > lo, hi - lo, 1.0)
    curve = [stop_hypervolume(returns[: 2 + t], lo, span) for t in range(9)]
    patience, gain = 2, 0.05
    expected = next((t for t in range(9) if should_stop(curve[: t + 1], patience, gain)), None)
    assert expected is not None and expected < 8  # the toy's curve flattens before its last iteration
    stopped = run(tiny_run(envs, iterations=8, stop_patience=patience, stop_min_gain=gain))
    assert stopped.stop_curve == curve[: expected + 1]  # the same computation on the same members
    assert stopped.stopped_at == expected and stopped.record() == {"stopped_at": expected}
    assert stopped.iteration == expected and len(stopped.members) == 2 + expected
    # what it made is the full run's first members (same streams)
    for a, b in zip(stopped.members, full.members):
        assert a.returns == b.returns
    # a gain no run reaches stops at the patience itself
    eager = run(tiny_run(envs, stop_patience=1, stop_min_gain=1e9))
    assert eager.stopped_at == 1 and eager.iteration == 1


# ---------------------------------------------------------------- aligned mixing (issue 61)


def test_an_aligned_hybrid_start_of_a_parent_and_its_permuted_copy_is_that_parent():
    """extract.align weights: the child's start mixes its parents after weight matching, the
    interpolation stage's implementation; a parent mixed with a permuted copy of itself gives it back."""
    from pipeline.core.alignment import MixOptions, _permuted

    buffers, _, actors = inputs()
    rng = np.random.default_rng(0)
    copy_of_0 = _permuted(actors[0], [rng.permutation(32), rng.permutation(32)])
    pair = [actors[0], copy_of_0]
    plain = ex.start_child(RETURNS[:2], pair, buffers, config(), np.random.default_rng(5), 77, "cpu")
    cfg = replace(config(), mixing=MixOptions(align="weights"))
    aligned = ex.start_child(RETURNS[:2], pair, buffers, cfg, np.random.default_rng(5), 77, "cpu")
    assert sorted(aligned.parents) == [0, 1] and aligned.parents == plain.parents and aligned.init == "interpolated"
    x = torch.from_numpy(buffers[0]["obs"][:64])
    with torch.no_grad():
        assert torch.allclose(aligned.actor(x), actors[0](x), atol=1e-5)
        assert not torch.allclose(plain.actor(x), actors[0](x), atol=1e-3)


def test_seeds_mixed_with_the_extract_options_are_the_interpolation_stage_s(envs):
    from pipeline.core.alignment import MixOptions, buffer_states, mixer

    r = run(tiny_run(envs, iterations=1, seed_interpolation=2, align="weights", repair=True, mix_states=128))
    seeds = [m for m in r.members if m.origin == "interpolated"]
    assert len(seeds) == 2
    make, line = mixer(
        [r.starts[0].actor, r.starts[1].actor],
        MixOptions(align="weights", repair=True),
        buffer_states(r.buffers, 128, 3),
    )
    assert line is None
    for m in seeds:
        assert all(torch.equal(m.actor[k], v) for k, v in make(m.target_weight).state_dict().items())
    assert r.record()["seed_interpolation"]["mixing"] == "aligned (weight matching), linear, REPAIR"
    # recorded only where set: a run at the defaults keeps its record
    dump = without_default_extensions(ExtractParams(align="weights").model_dump())
    assert dump["align"] == "weights" and "repair" not in dump and "mix" not in dump
