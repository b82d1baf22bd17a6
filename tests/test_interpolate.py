"""The weight-space interpolation baseline (pipeline/baselines/interpolate.py, stage interpolate)
and td3.shared_init, at library level: the grid, the mixing, its ends, the population it makes,
the one-line refusal of actors that cannot be mixed, and equal initial weights under shared init."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch
import yaml
from support.tiny_params import TINY, merge, save_params, with_lists

from pipeline.baselines.interpolate import (
    EVAL_STREAM,
    ORIGIN,
    architecture_problem,
    grid_resolution,
    interpolate,
    mix_actors,
    mixing_weights,
    simplex_points,
)
from pipeline.core.checkpoint import save_policy
from pipeline.core.envs import env_spec, make_env, spec_meta
from pipeline.core.nets import Actor, ScriptedActor
from pipeline.core.specialist import StartingPolicy
from pipeline.evaluation.episodes import eval_seeds, evaluate_policy
from pipeline.extraction import run as extraction_run
from pipeline.params import RunParams, section
from pipeline.params.methods import METHODS
from pipeline.params.planned import run_lists
from pipeline.params.runlists import derived_lists
from pipeline.params.td3 import TD3Params
from pipeline.params.tracked import tidied_text as synced_text
from pipeline.reporting.presentation import colour, label
from pipeline.reporting.runs import Run
from pipeline.reporting.verdicts import VERDICT_PAIRS, verdicts
from pipeline.specialists.td3 import init_stacked, run_seeds

ENV, CAP = "mo-halfcheetah-v5", 12
OBS, ACT = 17, 6
LOW, HIGH = [-1.0] * ACT, [1.0] * ACT


def actor(seed: int, hidden=(16, 16)) -> Actor:
    torch.manual_seed(seed)
    return Actor(OBS, ACT, list(hidden), LOW, HIGH).eval()


def params_of(a: torch.nn.Module) -> dict[str, torch.Tensor]:
    return {k: v for k, v in a.state_dict().items()}


@pytest.fixture(scope="module")
def envs():
    made = [make_env(ENV, CAP) for _ in range(2)]
    yield made
    for env in made:
        env.close()


# ---------------------------------------------------------------- the grid


def test_two_objective_grid_is_evenly_spaced_inside_and_as_long_as_the_children():
    for policies in (1, 5, 12, 48):
        w = mixing_weights(2, policies)
        assert len(w) == policies
        l = np.array([x[1] for x in w])  # noqa: E741 (the mixing weight's name in the issue)
        np.testing.assert_allclose(l, np.arange(1, policies + 1) / (policies + 1))
        np.testing.assert_allclose([x[0] + x[1] for x in w], 1.0)
    assert mixing_weights(2, 0) == []  # no children: the specialists alone


def test_simplex_grid_for_three_objectives_has_at_most_the_children_and_no_vertex():
    assert grid_resolution(3, 12) == 4 and len(mixing_weights(3, 12)) == 12
    assert grid_resolution(3, 48) == 8 and len(mixing_weights(3, 48)) == 42  # 52 at H = 9: too many
    assert len(mixing_weights(3, 2)) == 0  # H = 2 has 3 non-vertex points
    points = simplex_points(3, 4)
    assert len(set(points)) == len(points) and all(sum(k) == 4 and max(k) < 4 for k in points)
    # every pair of specialists gets its edge, and the inside is mixed from all three
    assert {(3, 1, 0), (2, 0, 2), (0, 1, 3), (2, 1, 1)} <= set(points)


# ---------------------------------------------------------------- mixing and its ends


def test_mixing_at_l_0_and_1_reproduces_each_specialist_exactly():
    a, b = actor(1), actor(2)
    obs = torch.randn(64, OBS, generator=torch.Generator().manual_seed(0))
    for weights, same in (([1.0, 0.0], a), ([0.0, 1.0], b)):
        mixed = mix_actors([a, b], weights)
        for key, value in params_of(same).items():
            assert torch.equal(params_of(mixed)[key], value), key
        with torch.no_grad():
            assert torch.equal(mixed(obs), same(obs))
    # between them: theta = (1 - l) theta_A + l theta_B, parameter by parameter
    mid = mix_actors([a, b], [0.75, 0.25])
    for key, value in params_of(a).items():
        torch.testing.assert_close(params_of(mid)[key], 0.75 * value + 0.25 * params_of(b)[key])
    # N = 3: each vertex of the simplex is its specialist
    c = actor(3)
    for k, same in enumerate((a, b, c)):
        w = [0.0, 0.0, 0.0]
        w[k] = 1.0
        assert all(
            torch.equal(x, y) for x, y in zip(params_of(mix_actors([a, b, c], w)).values(), params_of(same).values())
        )


def test_mixing_leaves_the_global_torch_generator_alone():
    a, b = actor(1), actor(2)
    before = torch.get_rng_state()
    mix_actors([a, b], [0.5, 0.5])
    assert torch.equal(torch.get_rng_state(), before)


def test_actors_that_cannot_be_mixed_get_one_line():
    small, big = actor(1, (16, 16)), actor(2, (32, 32))
    problem = architecture_problem([small, big], ["obj0", "obj1"])
    assert problem is not None and "\n" not in problem
    assert "one architecture" in problem and "(16, 17)" in problem and "(32, 17)" in problem
    with pytest.raises(ValueError, match="one architecture"):
        mix_actors([small, big], [0.5, 0.5])
    buf = io.BytesIO()
    torch.jit.save(torch.jit.script(small), buf)
    scripted = ScriptedActor.from_bytes(buf.getvalue(), LOW, HIGH)
    assert "ScriptedActor" in architecture_problem([small, scripted], ["obj0", "obj1"])
    bounds = Actor(OBS, ACT, [16, 16], [-2.0] * ACT, [2.0] * ACT)
    assert "action bounds" in architecture_problem([small, bounds], ["obj0", "obj1"])
    assert architecture_problem([small, actor(5)], ["obj0", "obj1"]) is None


# ---------------------------------------------------------------- the population


def test_population_starts_as_extractions_and_counts_only_its_evaluations(envs):
    assert EVAL_STREAM == extraction_run.EVAL_STREAM  # the same episodes as MAPEX's members
    a, b = actor(1), actor(2)
    starts = [StartingPolicy(0, "policy", a, [16, 16]), StartingPolicy(1, "policy", b, [16, 16])]
    members = interpolate(starts, 2, policies=5, per_iteration=2, eval_episodes=2, seed=3, envs=envs)
    assert [m.origin for m in members] == ["specialist"] * 2 + [ORIGIN] * 5
    assert [m.iteration for m in members] == [0, 0, 1, 1, 2, 2, 3]
    assert all(m.parents == [0, 1] for m in members[2:])
    np.testing.assert_allclose([m.target_weight[1] for m in members[2:]], np.arange(1, 6) / 6)
    # each member is evaluated on the episodes extraction evaluates its member of the same id on
    for i, m in enumerate(members):
        res = evaluate_policy(
            mix_actors([a, b], m.target_weight) if i >= 2 else (a, b)[i], envs, eval_seeds(3, 0, i, 2)
        )
        assert m.returns == res.mean.tolist()
    # its only frames: 7 policies x 2 episodes x 12 steps (HalfCheetah never terminates)
    assert [m.env_samples for m in members] == [24 * (i + 1) for i in range(7)]
    # an interpolated actor at l = 0 or 1 would be its specialist: the grid leaves the ends to them
    assert all(0 < m.target_weight[1] < 1 for m in members[2:])


def test_the_best_policy_of_a_set_is_the_one_mixed(envs):
    """A PDERL set holds several policies: the one with the highest return on its own objective is mixed."""
    weak, strong, other = actor(1), actor(2), actor(3)
    starts = [StartingPolicy(0, "pop0", weak, [16, 16]), StartingPolicy(0, "rl", strong, [16, 16])]
    starts.append(StartingPolicy(1, "rl", other, [16, 16]))
    members = interpolate(starts, 2, policies=1, per_iteration=1, eval_episodes=2, seed=0, envs=envs)
    best = max((0, 1), key=lambda i: members[i].returns[0])
    assert members[3].parents == [best, 2]
    mixed = mix_actors([(weak, strong)[best], other], [0.5, 0.5])
    assert all(torch.equal(torch.as_tensor(x), y) for x, y in zip(members[3].actor.values(), params_of(mixed).values()))


def test_stage_refuses_specialists_of_different_nets_in_one_line(cli, tmp_path):
    env = make_env(ENV, 40)
    meta = spec_meta(env_spec(env, ENV, 40))
    env.close()
    for k, hidden in enumerate(([16, 16], [32, 24])):
        (tmp_path / "spec" / f"obj{k}").mkdir(parents=True)
        net = Actor(meta["obs_dim"], meta["act_dim"], hidden, meta["action_low"], meta["action_high"])
        save_policy(
            tmp_path / "spec" / f"obj{k}" / "policy.pt", net, meta | {"hidden_sizes": hidden, "objective": k, "seed": 0}
        )
    policies = [{"objective": k, "file": f"models/obj{k}.zip", "format": "sb3"} for k in (0, 1)]
    run = {"methods": ["interpolate_imported"], "import_specialists": {"policies": policies}}
    params = tmp_path / "params.yaml"
    save_params(params, with_lists(merge(TINY, run)))
    r = cli(
        "interpolate",
        "--kind",
        "imported",
        "--specialists",
        tmp_path / "spec",
        "--out",
        tmp_path / "out",
        "--params",
        params,
    )
    assert r.exit_code == 2, r.output
    line = [x for x in r.output.splitlines() if x.startswith("error:")]
    assert len(line) == 1 and "cannot interpolate" in line[0] and "one architecture" in line[0], r.output
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------- the methods table and params


def test_interpolation_is_a_method_of_every_kind_with_its_own_stage_and_verdict():
    for kind in ("td3", "pderl", "imported"):
        m = METHODS[f"interpolate_{kind}"]
        assert (m.variant, m.kind, m.stage) == (None, kind, "interpolate")
        assert (
            label(m.name)
            == f"interpolation ({'PDERL' if kind == 'pderl' else kind.upper() if kind == 'td3' else kind})"
        )
    assert len({colour(m) for m in METHODS}) == len(METHODS)
    pairs = {(a, b) for a, b, _ in VERDICT_PAIRS}
    assert {("mapex_td3", "interpolate_td3"), ("mapex_pderl", "interpolate_pderl")} <= pairs
    assert ("mapex_posthoc_imported", "interpolate_imported") in pairs
    # a run of MAPEX-TD3 and interpolation gets its paired verdict in the report
    empty = np.zeros(0)
    runs = [
        Run(m, s, {"front": {"hypervolume": hv}, "iterations": 4}, np.zeros((0, 2)), empty, empty, empty, {}, None)
        for m, hvs in (("mapex_td3", [3.0, 5.1, 7.9]), ("interpolate_td3", [2.0, 4.0, 7.0]))
        for s, hv in enumerate(hvs)
    ]
    (verdict,) = verdicts(runs)
    assert (
        verdict.outcome == "beat"
        and "MAPEX-TD3 beat interpolation (TD3) on re-evaluated hypervolume" in verdict.sentence
    )


def _interpolations(lists: dict) -> list[str]:
    return [r["name"] for r in lists["method_runs"] if r["stage"] == "interpolate"]


def test_interpolation_stages_are_derived_and_the_plan_names_their_params():
    lists = derived_lists(["mapex_td3", "interpolate_td3", "interpolate_pderl"], [0, 1])
    assert _interpolations(lists) == ["interpolate_td3", "interpolate_pderl"]
    assert lists["td3_seeds"] == [0, 1] and lists["pderl_seeds"] == [0, 1]
    assert _interpolations(derived_lists(["mapex_td3", "warmup_only_td3"], [0])) == []
    with pytest.raises(ValueError, match="method_runs"):
        section({"seeds": [0], "methods": ["mapex_td3"], "method_runs": []}, "", RunParams)
    synced = synced_text("seeds: [0]\nmethods: [mapex_td3, interpolate_td3]\nextract:\n  beta: 0.5\n")
    raw = yaml.safe_load(synced)
    assert _interpolations(run_lists(raw)) == ["interpolate_td3"]
    assert raw["interpolate"] == {"policies": None, "eval_episodes": None}
    assert {"iterations", "children_per_iteration", "eval_episodes"} <= set(raw["extract"])
    assert raw["extract"]["beta"] == 0.5 and "warmup_lr" not in raw["extract"]  # only the keys it reads
    assert synced_text(synced) == synced
    assert "interpolate" not in yaml.safe_load(synced_text("seeds: [0]\nmethods: [mapex_td3, warmup_only_td3]\n"))


# ---------------------------------------------------------------- td3.shared_init


def test_shared_init_starts_every_objective_from_the_same_weights():
    env = make_env(ENV, CAP)
    spec = env_spec(env, ENV, CAP)
    env.close()
    cfg = TD3Params(learning_starts=40, batch_size=16, hidden_sizes=[16, 16])
    jobs = [(3, 0), (3, 1)]
    cpu = torch.device("cpu")

    def nets(state, s):
        e = state.critic.n_members // state.n
        return [
            *state.actor.unstack(s).state_dict().values(),
            *state.critic.subset(s * e, (s + 1) * e).state_dict().values(),
            *state.critic_target.subset(s * e, (s + 1) * e).state_dict().values(),
        ]

    for secondary in (True, False):
        shared = init_stacked(
            spec, cfg.model_copy(update={"shared_init": True, "secondary_critics": secondary}), jobs, cpu
        )
        assert all(torch.equal(x, y) for x, y in zip(nets(shared, 0), nets(shared, 1)))
        # a specialist alone (train_specialist.processes: one process per objective) starts the same
        alone = init_stacked(
            spec, cfg.model_copy(update={"shared_init": True, "secondary_critics": secondary}), [(3, 1)], cpu
        )
        assert all(torch.equal(x, y) for x, y in zip(nets(alone, 0), nets(shared, 1)))
    # off (the default): each objective from its own seed, as before the option existed
    default = init_stacked(spec, cfg, jobs, cpu)
    assert not all(torch.equal(x, y) for x, y in zip(nets(default, 0), nets(default, 1)))
    torch.manual_seed(run_seeds(3, 1)["torch"])
    own = Actor(spec.obs_dim, spec.act_dim, [16, 16], spec.action_low, spec.action_high)
    assert all(
        torch.equal(x, y) for x, y in zip(default.actor.unstack(1).state_dict().values(), own.state_dict().values())
    )
    # the other streams stay the objective's own
    assert run_seeds(3, 0)["numpy"] != run_seeds(3, 1)["numpy"]


def test_shared_init_off_leaves_the_recorded_td3_params_as_they_were():
    off = TD3Params().model_dump()
    assert "shared_init" not in off  # the specialists' metadata and fingerprints keep their bits
    assert TD3Params(shared_init=True).model_dump()["shared_init"] is True
    assert TD3Params(**TD3Params(shared_init=True).model_dump()).shared_init
