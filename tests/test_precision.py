"""The precision switch (pipeline/core/precision.py): `auto` resolves as documented (the CPU's
flags and CUDA mocked), every bf16 path runs on a tiny problem and stays finite with fp32 master
weights, optimizer state and outputs, the resume fingerprint and the recorded params change with
precision, and fp32 records what it recorded before the key existed.

No timings: that bf16 is faster where `auto` picks it is docs/benchmarks.md's ("Precision").
The fp32 paths' bits are checked elsewhere against frozen references (tests/support/
reference_child.py via test_extract_children.py, td3_update via test_batched_specialists.py).
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

import pipeline.core.precision as precision
from pipeline.core.envs import env_spec, make_env
from pipeline.core.nets import Actor, CriticEnsemble, ScriptedActor, StackedActor
from pipeline.core.precision import AUTO_MIN_WIDTH, compute, frozen, resolve, without_fp32
from pipeline.core.resume import run_fingerprint
from pipeline.core.seeding import derive_seeds
from pipeline.critics.posthoc import fit_posthoc_critics
from pipeline.evaluation.episodes import evaluate_policies
from pipeline.extraction.children import make_children
from pipeline.extraction.mapex import AdvantageConfig, ChildConfig, ChildSeeds, critic_values
from pipeline.params.fit_critics import FitCriticsParams
from pipeline.params.td3 import TD3Params
from pipeline.params.train_pderl import TrainPderlParams
from pipeline.params.train_specialist import TrainSpecialistParams
from pipeline.specialists.pderl import PderlRun
from pipeline.specialists.td3 import stack_td3
from pipeline.specialists.td3_learner import TD3Learner
from pipeline.specialists.td3_training import train_specialists

ENV, CAP = "mo-swimmer-v5", 30
OBS, ACT = 5, 3


@pytest.fixture
def flags(monkeypatch):
    """Set the CPU flags `native_bf16` sees: flags({"avx512_bf16"})."""

    def set_flags(names) -> None:
        monkeypatch.setattr(precision, "cpu_flags", lambda path=precision.CPUINFO: frozenset(names))

    return set_flags


# ---------------------------------------------------------------- resolution


@pytest.mark.parametrize("asked", ["fp32", "bf16"])
def test_fp32_and_bf16_resolve_as_asked_anywhere(flags, asked):
    flags(set())  # bf16 runs, emulated, without native support
    assert resolve(asked, "cpu", 64) == resolve(asked, "cpu", 256, workload="act") == asked


@pytest.mark.parametrize("flag", ["avx512_bf16", "amx_bf16"])
def test_auto_is_bf16_on_a_native_cpu_from_the_threshold_width(flags, flag):
    flags({"avx512f", flag})
    assert resolve("auto", "cpu", AUTO_MIN_WIDTH) == "bf16"
    assert resolve("auto", "cpu", 1024) == "bf16"
    assert resolve("auto", "cpu", AUTO_MIN_WIDTH - 1) == "fp32"  # overhead-bound: bf16 was slower there
    assert resolve("auto", "cpu", 1024, workload="act") == "fp32"  # a few rows per env step: no faster


def test_auto_is_fp32_without_native_bf16(flags):
    flags({"avx2", "avx512f", "avx512_vnni"})
    assert resolve("auto", "cpu", 1024) == "fp32"


def test_auto_on_cuda_follows_the_devices_bf16_support(flags, monkeypatch):
    flags(set())  # the CPU's flags do not matter for a CUDA device
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda including_emulation=True: True)
    assert resolve("auto", "cuda", 256) == "bf16" and resolve("auto", "cuda", 64) == "fp32"
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda including_emulation=True: including_emulation)
    assert resolve("auto", "cuda", 256) == "fp32"  # emulated bf16 (before Ampere) is not native


def test_a_bad_precision_is_an_error():
    with pytest.raises(ValueError, match="'fp16'"):
        resolve("fp16", "cpu", 256)


def test_cpu_flags_reads_the_flags_line(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nmodel name\t: Some CPU\nflags\t\t: fpu avx512f avx512_bf16 sse\n\n")
    assert precision.cpu_flags(info) == {"fpu", "avx512f", "avx512_bf16", "sse"}
    assert precision.cpu_flags(tmp_path / "missing") == frozenset()


# ---------------------------------------------------------------- frozen copies and autocast


def test_frozen_casts_the_weights_once_and_keeps_the_action_bounds_fp32():
    torch.manual_seed(0)
    actor = Actor(OBS, ACT, [8, 8], [-2.0] * ACT, [1.0] * ACT)
    assert frozen(actor, "fp32") is actor
    cast = frozen(actor, "bf16")
    assert cast is not actor and frozen(cast, "bf16") is cast  # already cast: no second copy
    assert all(p.dtype == torch.bfloat16 and not p.requires_grad for p in cast.parameters())
    assert cast.scale.dtype == cast.centre.dtype == torch.float32
    assert all(p.dtype == torch.float32 for p in actor.parameters())  # the original is untouched
    obs = torch.randn(4, OBS)
    a = cast(obs)
    assert a.dtype == torch.float32 and (a >= -2).all() and (a <= 1).all()
    torch.testing.assert_close(a, actor(obs), atol=0.05, rtol=0)


def test_frozen_leaves_modules_that_cannot_take_bf16_alone():
    scripted = ScriptedActor()
    assert frozen(scripted, "bf16") is scripted


def test_critic_values_under_autocast_on_a_cpu():
    """The issue's failure: index_put of bf16 Q-values into an fp32 output under autocast."""
    torch.manual_seed(0)
    critics = [CriticEnsemble(OBS, ACT, [16, 16], 4) for _ in range(2)]
    obs, act = torch.randn(10, OBS), torch.rand(10, ACT)
    origin = torch.tensor([0, 1] * 5)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        q = critic_values(critics, obs, act, origin)
    q_cast = critic_values([frozen(c, "bf16") for c in critics], obs, act, origin)
    exact = critic_values(critics, obs, act, origin)
    assert q.dtype == q_cast.dtype == torch.float32 and q.shape == (10, 2)
    torch.testing.assert_close(q, exact, atol=0.05, rtol=0.05)
    torch.testing.assert_close(q_cast, exact, atol=0.05, rtol=0.05)


def test_compute_is_no_region_at_all_for_fp32():
    with compute("fp32", "cpu"):
        assert not torch.is_autocast_enabled("cpu")
    with compute("bf16", "cpu"):
        assert torch.is_autocast_enabled("cpu")
        assert torch.get_autocast_dtype("cpu") == torch.bfloat16


# ---------------------------------------------------------------- bf16 paths, tiny runs


def all_finite(module) -> bool:
    return all(bool(torch.isfinite(p).all()) for p in module.parameters())


def fp32_weights(module) -> bool:
    return all(p.dtype == torch.float32 for p in module.parameters())


def spec_of():
    env = make_env(ENV, CAP)
    spec = env_spec(env, ENV, CAP)
    env.close()
    return spec


TD3 = TD3Params(learning_starts=40, batch_size=16, hidden_sizes=[16, 16], buffer_size=100)


def test_specialists_train_in_bf16_and_stay_finite():
    spec = spec_of()
    out = {}
    for p in ("fp32", "bf16"):
        envs = [make_env(ENV, CAP) for _ in range(2)]
        cfg = TrainSpecialistParams(total_steps=80, device="cpu", precision=p)
        out[p] = train_specialists(envs, spec, TD3, cfg, [(0, 0), (0, 1)], torch.device("cpu"))
        for env in envs:
            env.close()
    for r in out["bf16"]:
        for net in (r.actor, r.actor_target, r.critic, r.critic_target):
            assert all_finite(net) and fp32_weights(net)  # master weights stay fp32
    # it did compute in bf16: the same draws, other bits
    assert not torch.equal(out["bf16"][0].critic.weights[1], out["fp32"][0].critic.weights[1])
    torch.testing.assert_close(out["bf16"][0].critic.weights[1], out["fp32"][0].critic.weights[1], atol=0.05, rtol=0)


def test_the_rl_agent_of_pderl_and_mopderl_updates_in_bf16():
    spec = spec_of()
    torch.manual_seed(0)
    actor = Actor(spec.obs_dim, spec.act_dim, [16, 16], spec.action_low, spec.action_high)
    critic = CriticEnsemble(spec.obs_dim, spec.act_dim, [16, 16], 2 * spec.n_objectives)
    m = list(range(spec.n_objectives))
    state = stack_td3(TD3, [actor], [critic], [m], [0], torch.device("cpu"))
    learner = TD3Learner(spec, TD3, state, np.random.default_rng(0), 1, 2, "cpu", precision="bf16")
    rng = np.random.default_rng(1)
    for i in range(50):
        learner.add(
            rng.normal(size=spec.obs_dim).astype(np.float32),
            rng.uniform(-1, 1, spec.act_dim).astype(np.float32),
            rng.normal(size=spec.n_objectives),
            rng.normal(size=spec.obs_dim).astype(np.float32),
            False,
            i % 10 == 9,
            i // 10,
            i % 10,
        )
    learner.train(6)
    learner.check_finite(full=True)  # losses, weights, targets, Adam's moments, the buffer
    assert all(v.dtype == torch.float32 for v in learner.update.metrics.values())
    moments = [v for st in state.critic_opt.state.values() for v in st.values() if v.dim() > 0]
    assert moments and all(v.dtype == torch.float32 for v in moments)
    assert not torch.equal(learner.networks()[2].weights[0], critic.weights[0])


def test_pderl_runs_its_agent_in_the_resolved_precision(flags):
    env = make_env("mo-hopper-2obj-v5", 20)
    spec = env_spec(env, "mo-hopper-2obj-v5", 20)
    env.close()
    td3 = TD3Params(learning_starts=40, batch_size=16, hidden_sizes=[8], buffer_size=200)
    pderl = dict(
        total_frames=200,
        population_size=3,
        mini_buffer_size=100,
        crossover_transitions=64,
        crossover_batch_size=32,
        mutation_states=32,
        device="cpu",
    )
    assert PderlRun(spec, td3, TrainPderlParams(**pderl, precision="bf16"), 0, 0).agent.update.precision == "bf16"
    flags({"avx512_bf16"})
    auto = TrainPderlParams(**pderl, precision="auto")
    assert PderlRun(spec, td3, auto, 0, 0).agent.update.precision == "fp32"  # 8 units: below the threshold


def child_inputs():
    rng = np.random.default_rng(0)
    buffers = [
        {
            "obs": rng.normal(size=(300, OBS)).astype(np.float32),
            "action": rng.uniform(-1, 1, (300, ACT)).astype(np.float32),
        }
        for _ in range(2)
    ]
    torch.manual_seed(0)
    critics = [CriticEnsemble(OBS, ACT, [16, 16], 4).eval() for _ in range(2)]
    actors = [Actor(OBS, ACT, [16, 16], [-1] * ACT, [1] * ACT).eval() for _ in range(2)]
    return np.array([[10.0, -3.0], [-1.0, 2.0]]), actors, buffers, critics


@pytest.mark.parametrize("k", [1, 2])
@pytest.mark.parametrize("recompute", ["every_step", "once"])
def test_children_train_in_bf16_one_at_a_time_and_stacked(k, recompute):
    returns, actors, buffers, critics = child_inputs()
    before = [copy.deepcopy(c.state_dict()) for c in critics]
    adv = AdvantageConfig(
        epochs=2,
        beta=1.0,
        omega_max=2.0,
        lr=1e-3,
        batch_size=64,
        max_grad_norm=1.0,
        recompute=recompute,
        norm="zscore",
    )
    seeds = [ChildSeeds(*derive_seeds(0, c, n=3)) for c in range(k)]
    made = {}
    for p in ("fp32", "bf16"):
        cfg = ChildConfig(
            hidden_sizes=(16, 16),
            child_buffer_size=400,
            weight_norm="l2",
            warmup_steps=20,
            warmup_lr=1e-3,
            warmup_batch_size=64,
            adv=adv,
            precision=p,
        )
        made[p] = make_children(returns, actors, buffers, critics, cfg, seeds, "cpu")
    for (child, rec), (ref, _) in zip(made["bf16"], made["fp32"]):
        assert all_finite(child) and fp32_weights(child)
        assert np.isfinite(rec.stats["omega_mean"]) and 0 < rec.stats["omega_mean"] <= 2.0
        assert not all(torch.equal(x, y) for x, y in zip(child.parameters(), ref.parameters()))
    # the specialists' critics are read, never changed (a bf16 copy is made)
    assert all(torch.equal(v, c.state_dict()[n]) for b, c in zip(before, critics) for n, v in b.items())


def test_posthoc_critics_fit_in_bf16():
    rng = np.random.default_rng(0)
    n = 200
    data = {
        "obs": rng.normal(size=(n, OBS)).astype(np.float32),
        "action": rng.uniform(-1, 1, (n, ACT)).astype(np.float32),
        "reward": rng.normal(size=(n, 2)).astype(np.float32),
        "next_obs": rng.normal(size=(n, OBS)).astype(np.float32),
        "terminated": np.zeros(n, bool),
        "truncated": np.zeros(n, bool),
        "episode": np.zeros(n, np.int64),
        "episode_step": np.arange(n, dtype=np.int32),
    }
    torch.manual_seed(0)
    policy = Actor(OBS, ACT, [16], [-1] * ACT, [1] * ACT)
    fits = {}
    for p in ("fp32", "bf16"):
        cfg = FitCriticsParams(steps=30, check_every=0, batch_size=32, hidden_sizes=[16, 16], device="cpu", precision=p)
        fits[p] = fit_posthoc_critics(
            data, policy, [0, 1], cfg, np.random.default_rng(1), torch.Generator().manual_seed(2)
        )
    out = fits["bf16"]
    assert np.isfinite(out.final_loss) and out.steps == 30
    assert all_finite(out.online) and fp32_weights(out.online) and fp32_weights(out.target)
    assert not torch.equal(out.online.weights[0], fits["fp32"].online.weights[0])
    assert all(p.dtype == torch.float32 for p in policy.parameters())  # the target policy is copied, not cast


def test_evaluation_in_bf16_runs_one_and_several_policies():
    env_id = ENV
    envs = [make_env(env_id, CAP) for _ in range(4)]
    spec = env_spec(envs[0], env_id, CAP)
    torch.manual_seed(0)
    actors = [Actor(spec.obs_dim, spec.act_dim, [16], spec.action_low, spec.action_high) for _ in range(2)]
    for p in ("fp32", "bf16"):
        one = evaluate_policies(actors[:1], envs, [[1, 2]], p)
        two = evaluate_policies(actors, envs, [[1, 2], [3, 4]], p)
        assert np.isfinite(one[0].returns).all() and all(np.isfinite(r.returns).all() for r in two)
        assert one[0].env_samples == 2 * CAP
    assert all(p.dtype == torch.float32 for a in actors for p in a.parameters())
    for env in envs:
        env.close()
    # a stacked set of bf16 copies: bf16 weights, fp32 actions within the bounds
    stacked = StackedActor([frozen(a, "bf16") for a in actors])
    assert stacked.weights[0].dtype == torch.bfloat16
    out = stacked(torch.randn(2, 3, spec.obs_dim))
    assert out.dtype == torch.float32 and (out.abs() <= 1).all()


# ---------------------------------------------------------------- fingerprint and records


def test_the_resume_fingerprint_changes_with_precision():
    config = {"extract": {"precision": "auto"}, "seed": 0}
    fp32 = run_fingerprint("extract", config, "cpu", precision="fp32")
    assert run_fingerprint("extract", config, "cpu", precision="bf16") != fp32
    assert run_fingerprint("extract", config, "cpu") == fp32  # fp32 is the default
    assert run_fingerprint("extract", {**config, "extract": {"precision": "bf16"}}, "cpu") != fp32


def test_artifacts_record_precision_unless_fp32():
    assert without_fp32(TrainSpecialistParams().model_dump()) == {
        k: v for k, v in TrainSpecialistParams().model_dump().items() if k != "precision"
    }
    assert without_fp32(TrainSpecialistParams(precision="bf16").model_dump())["precision"] == "bf16"
    assert without_fp32(TrainSpecialistParams(precision="auto").model_dump())["precision"] == "auto"


@pytest.mark.parametrize(
    "section", ["train_specialist", "train_pderl", "mopderl", "fit_critics", "extract", "evaluate"]
)
def test_every_section_that_trains_or_evaluates_has_a_precision_defaulting_to_fp32(section):
    from pipeline.params.registry import section_models

    model = section_models()[section]
    assert model.model_fields["precision"].default == "fp32"
    with pytest.raises(ValueError):
        model.model_validate({"precision": "fp16"})
