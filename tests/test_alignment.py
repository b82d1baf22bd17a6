"""Aligned interpolation (pipeline/core/alignment.py, issue 61): weight matching, REPAIR, RegMean."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline.core.alignment import (
    MixOptions,
    _permuted,
    align_to_first,
    buffer_states,
    layer_inputs,
    mixer,
    regmean,
    repair,
    weight_matching,
)
from pipeline.core.mixing import mix_actors
from pipeline.core.nets import Actor, NormalizedActor

OBS, ACT = 11, 3


def actor(seed: int, hidden=(32, 24)) -> Actor:
    torch.manual_seed(seed)
    return Actor(OBS, ACT, list(hidden), -np.ones(ACT), np.ones(ACT))


def states(n=512, seed=0) -> torch.Tensor:
    return torch.from_numpy(np.random.default_rng(seed).normal(size=(n, OBS)).astype(np.float32))


@pytest.mark.parametrize("hidden", [(32,), (32, 24), (16, 16, 16)])
def test_weight_matching_recovers_a_permuted_copy_exactly(hidden):
    a = actor(1, hidden)
    rng = np.random.default_rng(7)
    perms = [rng.permutation(h) for h in hidden]
    b = _permuted(a, perms)
    x = states()
    with torch.no_grad():
        assert torch.allclose(a(x), b(x), atol=1e-6)  # a permutation keeps the function
        assert not torch.equal(a.net[0].weight, b.net[0].weight)
    found = weight_matching(a, b)
    # b's unit i is a's unit perms[i]; matching b back onto a needs the inverse
    for p, f in zip(perms, found):
        assert np.array_equal(p[f], np.arange(len(p)))
    back = align_to_first([a, b])[1]
    for name, value in a.state_dict().items():
        assert torch.equal(value, back.state_dict()[name]), name
    with torch.no_grad():
        assert torch.allclose(back(x), b(x), atol=1e-6)


def test_alignment_keeps_each_actor_s_function_and_brings_independent_actors_closer():
    a, b = actor(1), actor(2)
    aligned = align_to_first([a, b])[1]
    x = states()
    with torch.no_grad():
        assert torch.allclose(aligned(x), b(x), atol=1e-5)

    def distance(u, v):
        return sum(float((p - q).pow(2).sum()) for p, q in zip(u.parameters(), v.parameters()))

    assert distance(a, aligned) < distance(a, b)


def test_repair_gives_the_mix_the_endpoints_statistics_on_the_states():
    a, b = actor(1), actor(2)
    x = states(2048)
    w = [0.3, 0.7]
    mixed = mix_actors([a, b], w)
    fixed = repair(mixed, [a, b], w, x)
    _, pre_a = layer_inputs(a, x)
    _, pre_b = layer_inputs(b, x)
    _, pre_m = layer_inputs(fixed, x)
    _, pre_plain = layer_inputs(mixed, x)
    for za, zb, zm, zp in zip(pre_a, pre_b, pre_m, pre_plain):
        mean_t = w[0] * za.double().mean(0) + w[1] * zb.double().mean(0)
        std_t = w[0] * za.double().std(0, unbiased=False) + w[1] * zb.double().std(0, unbiased=False)
        assert torch.allclose(zm.double().mean(0), mean_t, atol=1e-4)
        assert torch.allclose(zm.double().std(0, unbiased=False), std_t, rtol=1e-4, atol=1e-5)
        # the plain mix did not have them (the test can fail)
        assert not torch.allclose(zp.double().std(0, unbiased=False), std_t, rtol=1e-2)


def test_repair_at_a_vertex_changes_nothing_that_matters():
    a, b = actor(1), actor(2)
    x = states()
    fixed = repair(mix_actors([a, b], [1.0, 0.0]), [a], [1.0], x)
    with torch.no_grad():
        assert torch.allclose(fixed(x), a(x), atol=1e-5)


def test_regmean_of_identical_networks_is_that_network():
    a = actor(3)
    x = states(1024)
    merged = regmean([a, a], [0.5, 0.5], x, alpha=0.9)
    for name, value in a.state_dict().items():
        assert torch.allclose(value, merged.state_dict()[name], atol=1e-4), name


def test_regmean_differs_from_the_linear_mix_and_reproduces_outputs_better():
    a, b = actor(1, (32,)), actor(2, (32,))
    x = states(2048)
    merged = regmean([a, b], [0.5, 0.5], x, alpha=1.0)
    linear = mix_actors([a, b], [0.5, 0.5])
    # on the input layer, RegMean is the least-squares fit of both endpoints' preactivations
    ins = torch.cat([x, torch.ones(len(x), 1)], 1).double()

    def fit_error(layer):
        theta = torch.cat([layer.weight, layer.bias[:, None]], 1).double()
        err = 0.0
        for end in (a, b):
            t = torch.cat([end.net[0].weight, end.net[0].bias[:, None]], 1).double()
            err += float(((ins @ theta.T) - (ins @ t.T)).pow(2).sum())
        return err

    assert fit_error(merged.net[0]) <= fit_error(linear.net[0]) * (1 + 1e-9)


def test_mixer_composes_the_options_and_the_plain_options_are_the_linear_mix():
    a, b = actor(1), actor(2)
    x = states()
    make, line = mixer([a, b], MixOptions(), x)
    assert line is None
    plain = mix_actors([a, b], [0.5, 0.5])
    for name, value in plain.state_dict().items():
        assert torch.equal(value, make([0.5, 0.5]).state_dict()[name])
    make, line = mixer([a, b], MixOptions(align="weights", repair=True), x)
    assert line is None
    m = make([0.5, 0.5])
    assert not torch.equal(m.net[0].weight, plain.net[0].weight)
    # a vertex of the aligned path is that specialist's function
    with torch.no_grad():
        assert torch.allclose(make([0.0, 1.0])(x), b(x), atol=1e-5)
    with pytest.raises(ValueError, match="need states"):
        mixer([a, b], MixOptions(repair=True), None)


def test_an_actor_that_cannot_be_aligned_falls_back_with_one_line():
    a, b = actor(1), actor(2)
    for net in (a, b):
        net.net[1] = torch.nn.Tanh()
    make, line = mixer([a, b], MixOptions(align="weights", repair=True), states())
    assert line is not None and "\n" not in line
    assert "Tanh" in line and "mixed linearly, unaligned and unrepaired" in line
    plain = mix_actors([a, b], [0.25, 0.75])
    for name, value in plain.state_dict().items():
        assert torch.equal(value, make([0.25, 0.75]).state_dict()[name])


def test_normalized_actors_align_on_their_normalised_inputs():
    mean, std = np.linspace(-1, 1, OBS), np.linspace(0.5, 2, OBS)
    torch.manual_seed(1)
    a = NormalizedActor(OBS, ACT, [16, 16], -np.ones(ACT), np.ones(ACT), mean, std, 10.0)
    b = _permuted(a, [np.random.default_rng(0).permutation(16), np.random.default_rng(1).permutation(16)])
    x = states() * 3 + 1
    make, line = mixer([a, b], MixOptions(align="weights", repair=True), x)
    assert line is None
    with torch.no_grad():
        assert torch.allclose(make([0.5, 0.5])(x), a(x), atol=1e-5)


def test_buffer_states_are_equal_shares_and_deterministic():
    bufs = [{"obs": np.full((100, OBS), k, np.float32)} for k in range(2)]
    s1, s2 = buffer_states(bufs, 40, 5), buffer_states(bufs, 40, 5)
    assert torch.equal(s1, s2) and s1.shape == (40, OBS)
    assert int((s1[:, 0] == 0).sum()) == 20 and int((s1[:, 0] == 1).sum()) == 20
    assert buffer_states([{"obs": np.zeros((3, OBS), np.float32)}], 40, 0).shape == (3, OBS)


# ---------------------------------------------------------------- the stage


def _slots(tmp_path, with_buffer=(True, True)):
    from pipeline.core.buffer import FIELDS, save_buffer
    from pipeline.core.checkpoint import save_policy
    from pipeline.core.envs import env_spec, make_env, spec_meta

    env = make_env("mo-halfcheetah-v5", 40)
    meta = spec_meta(env_spec(env, "mo-halfcheetah-v5", 40))
    env.close()
    obs_dim, act_dim = meta["obs_dim"], meta["act_dim"]
    rng = np.random.default_rng(0)
    for k in (0, 1):
        slot = tmp_path / "spec" / f"obj{k}"
        slot.mkdir(parents=True)
        torch.manual_seed(10 + k)
        net = Actor(obs_dim, act_dim, [16, 16], meta["action_low"], meta["action_high"])
        save_policy(slot / "policy.pt", net, meta | {"hidden_sizes": [16, 16], "objective": k, "seed": 0})
        if with_buffer[k]:
            n = 200
            data = {
                "obs": rng.normal(size=(n, obs_dim)).astype(np.float32),
                "action": rng.uniform(-1, 1, (n, act_dim)).astype(np.float32),
                "reward": rng.normal(size=(n, 2)).astype(np.float32),
                "next_obs": rng.normal(size=(n, obs_dim)).astype(np.float32),
                "terminated": np.zeros(n, bool),
                "truncated": np.zeros(n, bool),
                "episode": np.zeros(n, np.int64),
                "episode_step": np.arange(n, dtype=np.int32),
            }
            assert set(data) == set(FIELDS)
            attrs = {key: meta[key] for key in ("env_id", "obs_dim", "act_dim", "n_objectives")}
            save_buffer(slot / "buffer.zarr", data, attrs | {"max_episode_steps": 40, "seed": 0, "objective": k})
    return tmp_path / "spec"


def _stage(cli, tmp_path, spec, interpolate):
    from support.tiny_params import TINY, merge, save_params, with_lists

    params = tmp_path / "params.yaml"
    save_params(params, with_lists(merge(TINY, {"methods": ["interpolate_td3"], "interpolate": interpolate})))
    return cli("interpolate", "--specialists", spec, "--out", tmp_path / "out", "--params", params)


def test_stage_mixes_aligned_and_repaired_policies_and_says_so(cli, tmp_path):
    from pipeline.core.population import load_population

    spec = _slots(tmp_path)
    r = _stage(cli, tmp_path, spec, {"policies": 3, "align": "weights", "repair": True, "states": 64})
    assert r.exit_code == 0, r.output
    members, meta = load_population(tmp_path / "out" / "population.pt")
    assert meta["mixing"] == "aligned (weight matching), linear, REPAIR" and "mixing_fallback" not in meta
    assert meta["params"]["interpolate"]["align"] == "weights" and meta["params"]["interpolate"]["states"] == 64
    assert [m.origin for m in members] == ["specialist"] * 2 + ["interpolated"] * 3
    # the middle policy is not the plain mix (alignment and REPAIR changed it)
    plain = _stage(cli, tmp_path / "plain", _slots(tmp_path / "plain"), {"policies": 3})
    assert plain.exit_code == 0, plain.output
    plain_members, plain_meta = load_population(tmp_path / "plain" / "out" / "population.pt")
    assert "mixing" not in plain_meta and set(plain_meta["params"]["interpolate"]) == {"policies", "eval_episodes"}
    key = next(k for k in members[3].actor if k.endswith("0.weight"))
    assert not torch.equal(members[3].actor[key], plain_members[3].actor[key])


def test_stage_without_a_buffer_for_repair_names_the_slot_in_one_line(cli, tmp_path):
    spec = _slots(tmp_path, with_buffer=(True, False))
    r = _stage(cli, tmp_path, spec, {"policies": 2, "mix": "regmean"})
    assert r.exit_code == 2, r.output
    line = [x for x in r.output.splitlines() if x.startswith("error:")]
    assert len(line) == 1 and "obj1/buffer.zarr" in line[0] and "no replay buffer" in line[0], r.output
    assert not (tmp_path / "out").exists()
    # aligning alone reads no buffer
    assert _stage(cli, tmp_path, spec, {"policies": 2, "align": "weights"}).exit_code == 0


# ---------------------------------------------------------------- the barrier on the report


def _run(method, origin, objective, returns):
    from pipeline.reporting.runs import Run

    n = len(origin)
    return Run(
        method=method,
        seed=0,
        metrics={},
        returns=np.asarray(returns, float),
        origin=np.asarray(origin),
        iteration=np.zeros(n, int),
        on_front=np.ones(n, bool),
        history={},
        objective=np.asarray(objective),
    )


def test_the_interpolation_path_runs_from_the_mixed_specialists_in_grid_order():
    from pipeline.reporting.figures import barrier_figure, interpolation_path

    # a PDERL-like set: two policies of objective 0 (the second is better on it), one of objective 1
    r = _run(
        "interpolate_td3",
        ["specialist", "specialist", "specialist", "interpolated", "interpolated", "interpolated"],
        [0, 0, 1, -1, -1, -1],
        [[5, -9], [8, -9], [0, -1], [6, -7], [3, -5], [1, -2]],
    )
    lam, ret = interpolation_path(r)
    np.testing.assert_allclose(lam, [0, 0.25, 0.5, 0.75, 1])
    np.testing.assert_allclose(ret[:, 0], [8, 6, 3, 1, 0])
    child = _run("mapex_td3", ["specialist", "specialist", "child"], [0, 1, -1], [[5, -9], [0, -1], [3, -3]])
    assert interpolation_path(child) is None
    assert barrier_figure([child], ["a", "b"], "env", 0, 8.0) is None
    fig = barrier_figure([r, child], ["a", "b"], "env", 0, 8.0)
    lines = [ln for ln in fig.axes[0].get_lines() if ln.get_label() != "straight line between the specialists"]
    assert len(lines) == 1 and list(lines[0].get_ydata()) == [8, 6, 3, 1, 0]
