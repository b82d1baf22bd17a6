"""Bring your own specialists (SB3, CleanRL, TorchScript) in; take the front's policies out.

Real SB3 models are trained for a few hundred steps inside the tests (stable-baselines3 is a
test extra, never a core dependency); the CleanRL checkpoints are built here in CleanRL's
layout (its actor modules, saved as CleanRL's --save-model does: a tuple of state dicts).
"""

from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from pipeline.core.artifacts import ArtifactError
from pipeline.core.buffer import load_buffer
from pipeline.core.checkpoint import load_policy
from pipeline.core.envs import env_spec, make_env
from pipeline.core.nets import Actor, ExportedActor, ScriptedActor
from pipeline.core.population import Member, load_population, member_actor, save_population
from pipeline.interop.collect import COLLECT_STREAM, CollectionRun
from pipeline.interop.readers import read_policy

# SB3 training and `dvc repro` from imported specialists: `make test-fast` leaves this file out.
pytestmark = pytest.mark.integration

sb3 = pytest.importorskip("stable_baselines3")

ENV = "mo-halfcheetah-v5"
STEPS = 40  # episode cap of these tests


@pytest.fixture(scope="module")
def spec():
    env = make_env(ENV, STEPS)
    s = env_spec(env, ENV, STEPS)
    env.close()
    return s


def scalar_env(objective: int):
    import mo_gymnasium as mo
    from mo_gymnasium.wrappers import LinearReward

    weight = np.eye(2, dtype=np.float32)[objective]
    return LinearReward(mo.make(ENV, max_episode_steps=STEPS), weight=weight)


@pytest.fixture(scope="module")
def sb3_models(tmp_path_factory) -> dict[str, Path]:
    """TD3 (objective 0) and SAC (objective 1) trained for 200 steps, saved as model.zip."""
    root = tmp_path_factory.mktemp("sb3")
    out = {}
    for name, cls, k in (("td3", sb3.TD3, 0), ("sac", sb3.SAC, 1)):
        model = cls(
            "MlpPolicy", scalar_env(k), learning_starts=100, policy_kwargs={"net_arch": [32, 24]}, seed=k, device="cpu"
        )
        model.learn(200)
        model.save(root / f"{name}.zip")
        out[name] = root / f"{name}.zip"
    return out


def random_obs(n: int = 100, dim: int = 17, seed: int = 0) -> np.ndarray:
    return (np.random.default_rng(seed).normal(size=(n, dim)) * 3).astype(np.float32)


@pytest.mark.parametrize("algo", ["td3", "sac"])
def test_sb3_actions_equal_predict(algo, sb3_models, spec):
    path = sb3_models[algo]
    imported = read_policy(path, "sb3", spec)
    assert imported.architecture == "mlp" and imported.hidden_sizes == [32, 24]
    assert imported.source["algorithm"] == algo and imported.source["library"] == "stable-baselines3"
    model = (sb3.TD3 if algo == "td3" else sb3.SAC).load(path, device="cpu")
    obs = random_obs()
    ref, _ = model.predict(obs, deterministic=True)
    with torch.no_grad():
        ours = imported.actor(torch.from_numpy(obs)).numpy()
    np.testing.assert_allclose(ours, ref, atol=1e-5, rtol=0)
    assert np.abs(ref).max() > 0.05  # not a trivially zero policy


class CleanRLTD3Actor(nn.Module):
    """CleanRL's td3_continuous_action.py Actor (its layer names and rescaling)."""

    def __init__(self, obs_dim, act_dim, low, high):
        super().__init__()
        self.fc1, self.fc2, self.fc_mu = nn.Linear(obs_dim, 48), nn.Linear(48, 40), nn.Linear(40, act_dim)
        self.register_buffer("action_scale", torch.tensor((high - low) / 2.0, dtype=torch.float32))
        self.register_buffer("action_bias", torch.tensor((high + low) / 2.0, dtype=torch.float32))

    def forward(self, x):
        x = torch.relu(self.fc2(torch.relu(self.fc1(x))))
        return torch.tanh(self.fc_mu(x)) * self.action_scale + self.action_bias


class CleanRLSACActor(CleanRLTD3Actor):
    """CleanRL's sac_continuous_action.py Actor: fc_mean and fc_logstd; the mean action squashed."""

    def __init__(self, obs_dim, act_dim, low, high):
        super().__init__(obs_dim, act_dim, low, high)
        del self.fc_mu
        self.fc_mean, self.fc_logstd = nn.Linear(40, act_dim), nn.Linear(40, act_dim)

    def forward(self, x):
        x = torch.relu(self.fc2(torch.relu(self.fc1(x))))
        return torch.tanh(self.fc_mean(x)) * self.action_scale + self.action_bias


@pytest.mark.parametrize("cls", [CleanRLTD3Actor, CleanRLSACActor])
def test_cleanrl_checkpoint_equals_its_actor(cls, spec, tmp_path):
    torch.manual_seed(0)
    low, high = np.array(spec.action_low), np.array(spec.action_high)
    actor = cls(spec.obs_dim, spec.act_dim, low, high)
    qf = nn.Sequential(nn.Linear(spec.obs_dim + spec.act_dim, 8), nn.ReLU(), nn.Linear(8, 1))
    path = tmp_path / "run.cleanrl_model"
    torch.save((actor.state_dict(), qf.state_dict(), qf.state_dict()), path)  # as CleanRL's --save-model
    imported = read_policy(path, "cleanrl", spec)
    assert imported.hidden_sizes == [48, 40]
    x = torch.from_numpy(random_obs())
    with torch.no_grad():
        np.testing.assert_allclose(imported.actor(x).numpy(), actor(x).numpy(), atol=1e-5, rtol=0)


class OddPolicy(nn.Module):
    """Any architecture will do for TorchScript: a LayerNorm and a tanh, rescaled to the bounds."""

    def __init__(self, obs_dim, act_dim):
        super().__init__()
        self.norm, self.lin = nn.LayerNorm(obs_dim), nn.Linear(obs_dim, act_dim)

    def forward(self, obs):
        return torch.tanh(self.lin(self.norm(obs)))


def scripted_file(tmp_path: Path, spec) -> tuple[Path, torch.jit.ScriptModule]:
    torch.manual_seed(1)
    module = torch.jit.script(OddPolicy(spec.obs_dim, spec.act_dim))
    path = tmp_path / "policy.ts"
    torch.jit.save(module, path)
    return path, module


def test_torchscript_actor_imports_and_round_trips(spec, tmp_path):
    path, module = scripted_file(tmp_path, spec)
    imported = read_policy(path, "torchscript", spec)
    assert isinstance(imported.actor, ScriptedActor) and imported.architecture == "torchscript"
    x = torch.from_numpy(random_obs())
    with torch.no_grad():
        assert torch.equal(imported.actor(x), module(x))
    # as a population member: the state dict is the file's bytes, read back with weights_only=True
    member = Member(
        "specialist", 0, 0, [], None, [0.0, 0.0], [0.0, 0.0], 1, 0, [], imported.actor.state_dict(), "policy"
    )
    save_population(tmp_path / "population.pt", [member], {"n_objectives": 2, "obs_dim": spec.obs_dim})
    (back,), meta = load_population(tmp_path / "population.pt")
    with torch.no_grad():
        assert torch.equal(member_actor(back, meta)(x), module(x))
    assert back.actor[ScriptedActor.KEY].numpy().tobytes() == path.read_bytes()


def test_a_frozen_torchscript_policy_without_parameters_imports_and_evaluates(cli, spec, tmp_path):
    """torch.jit.freeze turns the weights into constants: no parameters left. The import, the
    slot it writes and an evaluation of that slot's policy all work."""
    from pipeline.evaluation.episodes import evaluate_policies

    torch.manual_seed(1)
    frozen = torch.jit.freeze(torch.jit.script(OddPolicy(spec.obs_dim, spec.act_dim).eval()))
    assert not list(frozen.parameters())
    path = tmp_path / "frozen.ts"
    torch.jit.save(frozen, path)
    result, out = run_import(cli, tmp_path, path, "torchscript")
    assert result.exit_code == 0, result.output
    actor, meta = load_policy(out / "policy.pt")
    assert isinstance(actor, ScriptedActor) and not list(actor.parameters())
    x = torch.from_numpy(random_obs())
    with torch.no_grad():
        assert torch.equal(actor(x), frozen(x))
    envs = [make_env(ENV, STEPS) for _ in range(2)]
    (res,) = evaluate_policies([actor], envs, [[5, 6]])
    assert res.returns.shape == (2, 2) and np.isfinite(res.returns).all() and res.env_samples == 2 * STEPS
    for env in envs:
        env.close()


def exported_file(tmp_path: Path, spec, dynamic: bool = True) -> tuple[Path, nn.Module]:
    """OddPolicy as a torch.export program (.pt2), its batch axis dynamic unless told."""
    torch.manual_seed(3)
    module = OddPolicy(spec.obs_dim, spec.act_dim).eval()
    shapes = ({0: torch.export.Dim("batch")},) if dynamic else None
    program = torch.export.export(module, (torch.zeros(2, spec.obs_dim),), dynamic_shapes=shapes)
    path = tmp_path / ("policy.pt2" if dynamic else "static.pt2")
    torch.export.save(program, path)
    return path, module


def test_torch_export_program_imports_round_trips_and_exports_as_itself(cli, spec, tmp_path):
    path, module = exported_file(tmp_path, spec)
    imported = read_policy(path, "torch_export", spec)
    assert isinstance(imported.actor, ExportedActor) and imported.architecture == "torch_export"
    assert imported.source["format"] == "torch_export" and imported.hidden_sizes == []
    x = torch.from_numpy(random_obs())
    with torch.no_grad():
        np.testing.assert_allclose(imported.actor(x).numpy(), module(x).numpy(), atol=1e-6, rtol=0)
    # the stage's slot, read back with weights_only=True, then evaluated
    result, out = run_import(cli, tmp_path, path, "torch_export")
    assert result.exit_code == 0, result.output
    actor, meta = load_policy(out / "policy.pt")
    assert isinstance(actor, ExportedActor) and meta["architecture"] == "torch_export"
    assert actor.state_dict()[ExportedActor.KEY].numpy().tobytes() == path.read_bytes()
    from pipeline.evaluation.episodes import evaluate_policies

    envs = [make_env(ENV, STEPS)]
    (res,) = evaluate_policies([copy.deepcopy(actor)], envs, [[0]])
    assert np.isfinite(res.returns).all() and res.env_samples == STEPS
    envs[0].close()
    # as a population member: exported back as its own .pt2, with TorchScript traced from it
    population = tiny_population(tmp_path, spec, with_program=path)
    evaluated = fake_evaluation(tmp_path, population)
    front = tmp_path / "export"
    args = ["export", "--population", population, "--evaluated", evaluated, "--out", front]
    result = cli(*args, "--params", params_file(tmp_path))
    assert result.exit_code == 0, result.output
    (p1,) = [p for p in json.loads((front / "front.json").read_text())["policies"] if p["id"] == 1]
    assert (front / p1["pt2_file"]).read_bytes() == path.read_bytes()
    with torch.no_grad():
        traced, want = torch.jit.load(front / p1["file"])(x).numpy(), module(x).numpy()
    np.testing.assert_allclose(traced, want, atol=1e-6, rtol=0)


def test_import_refuses_a_bad_torch_export_file(cli, spec, tmp_path):
    text = tmp_path / "notes.pt2"
    text.write_text("not a program\n")
    static, _ = exported_file(tmp_path, spec, dynamic=False)  # exported for a batch of 2 only
    for path, says in (
        (text, "torch.export archive refused: not a zip archive"),  # inspected before torch reads it
        (static, f"the policy fails on a batch of {spec.obs_dim}-d observations"),
    ):
        result, out = run_import(cli, tmp_path, path, "torch_export")
        assert result.exit_code == 2, result.output
        errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
        assert len(errors) == 1 and errors[0].startswith(f"error: {path}: {says}"), errors
        assert not out.exists() or not any(out.iterdir())


def test_collection_writes_the_rewards_the_env_returned(sb3_models, spec):
    """Replay the collected actions in a fresh env with the collection's seed: the same
    observations, reward vectors, terminations and truncations come back."""
    from pipeline.core.seeding import derive_seeds

    imported = read_policy(sb3_models["td3"], "sb3", spec)
    run = CollectionRun(imported.actor, make_env(ENV, STEPS), spec, rows=90, noise=0.1, seed=3, objective=0)
    while not run.done:
        run.step()
    data = run.data()
    assert data["reward"].shape == (90, 2) and len(run.returns) == 2  # two 40-step episodes, 10 rows more
    assert data["truncated"].sum() == 2 and not data["terminated"].any()
    env = make_env(ENV, STEPS)
    obs, _ = env.reset(seed=derive_seeds(3, 0, COLLECT_STREAM, n=3)[1])
    for i in range(45):
        np.testing.assert_array_equal(data["obs"][i], np.asarray(obs, np.float32))
        obs, reward, terminated, truncated, _ = env.step(data["action"][i])
        np.testing.assert_array_equal(data["reward"][i], np.asarray(reward, np.float32))
        assert (data["terminated"][i], data["truncated"][i]) == (terminated, truncated)
        if terminated or truncated:
            obs, _ = env.reset()
    # the noise is there (actions differ from the policy's), inside the bounds
    with torch.no_grad():
        clean = imported.actor(torch.from_numpy(data["obs"])).numpy()
    assert np.abs(data["action"] - clean).max() > 0.01 and np.abs(data["action"]).max() <= 1.0


def test_collection_resumes_to_the_same_rows(sb3_models, spec):
    imported = read_policy(sb3_models["sac"], "sb3", spec)

    def fresh():
        return CollectionRun(imported.actor, make_env(ENV, STEPS), spec, rows=70, noise=0.1, seed=0, objective=1)

    whole = fresh()
    while not whole.done:
        whole.step()
    cut = fresh()
    for _ in range(33):  # mid-episode
        cut.step()
    state = cut.state_dict()
    torch.save(state, "/dev/null")  # picklable as the checkpoint writes it
    resumed = fresh()
    resumed.load_state_dict(state)
    while not resumed.done:
        resumed.step()
    for key, value in whole.data().items():
        np.testing.assert_array_equal(resumed.data()[key], value, err_msg=key)


# -- the stage: bad inputs, each one line naming the file, nothing written ----------------------


class GoesNaN(nn.Module):
    """Finite on the import's probe batch (call 1), then NaN from its `after`-th call on."""

    def __init__(self, act_dim: int, after: int):
        super().__init__()
        self.act_dim, self.after, self.calls = act_dim, after, 0

    def forward(self, obs):
        self.calls += 1
        out = torch.zeros(obs.shape[0], self.act_dim)
        return out * float("nan") if self.calls >= self.after else out


def params_file(tmp_path: Path, rows: int = 60) -> Path:
    import yaml

    p = {
        "env": {"id": ENV, "max_episode_steps": STEPS},
        "seeds": [0],
        "methods": ["mapex_td3"],
        "import_specialists": {"collect_rows": rows},
    }
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(p))
    return path


def run_import(cli, tmp_path, file, fmt, objective=0, buffer=None):
    out = tmp_path / "out" / f"obj{objective}"
    args = ["import-specialist", "--objective", objective, "--file", file, "--format", fmt, "--out", out]
    args += ["--params", params_file(tmp_path)] + (["--buffer", buffer] if buffer else [])
    return cli(*args), out


def test_import_stage_writes_a_slot(cli, sb3_models, tmp_path):
    result, out = run_import(cli, tmp_path, sb3_models["td3"], "sb3")
    assert result.exit_code == 0, result.output
    actor, meta = load_policy(out / "policy.pt")  # weights_only=True inside
    assert meta["source"]["format"] == "sb3" and meta["collection_frames"] == 60 and meta["objective"] == 0
    # only what the stage's declared inputs and params fix: no provenance, no undeclared param
    assert "provenance" not in meta and set(meta["params"]["env"]) == {"id", "max_episode_steps", "reward_terms"}
    assert meta["params"]["import_specialists"] == {"collect_rows": 60, "exploration_noise": 0.1}
    data, attrs = load_buffer(out / "buffer.zarr")
    assert "provenance" not in attrs
    assert attrs["n_transitions"] == 60 and data["reward"].shape == (60, 2) and attrs["collection_frames"] == 60
    assert (out / "collect.csv").read_text().startswith("episode,obj0,obj1\n")


def test_collection_stops_at_a_non_finite_action_naming_the_file_and_row(cli, spec, tmp_path):
    path = tmp_path / "goes_nan.ts"
    torch.jit.save(torch.jit.script(GoesNaN(spec.act_dim, after=12)), path)  # row 10: call 12
    result, out = run_import(cli, tmp_path, path, "torchscript")
    assert result.exit_code == 2, result.output
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert errors == [
        f"error: {path}: the policy returned a non-finite action (nan, nan, nan) at row 10 "
        "(episode 0, step 10); collection stopped, no buffer written"
    ]
    assert "Traceback" not in result.stderr and not (out / "buffer.zarr").exists()


def test_import_refuses_a_discrete_action_model(cli, tmp_path):
    import gymnasium as gym

    model = sb3.DQN("MlpPolicy", gym.make("CartPole-v1"), learning_starts=1000, seed=0, device="cpu")
    model.save(tmp_path / "dqn.zip")
    result, out = run_import(cli, tmp_path, tmp_path / "dqn.zip", "sb3")
    assert result.exit_code == 2
    line = result.output.strip().splitlines()[-1]
    assert "dqn.zip" in line and "Discrete" in line and "continuous Box" in line
    assert not out.exists()


def test_import_refuses_a_model_of_another_env(cli, tmp_path):
    import gymnasium as gym

    model = sb3.TD3("MlpPolicy", gym.make("Pendulum-v1"), learning_starts=1000, seed=0, device="cpu")
    model.save(tmp_path / "pendulum.zip")
    result, out = run_import(cli, tmp_path, tmp_path / "pendulum.zip", "sb3")
    assert result.exit_code == 2
    line = result.output.strip().splitlines()[-1]
    assert "pendulum.zip" in line and "3-d observations" in line and "17" in line
    assert not out.exists()


def test_import_refuses_a_corrupted_zip(cli, sb3_models, tmp_path):
    bad = tmp_path / "broken.zip"
    bad.write_bytes(sb3_models["td3"].read_bytes()[:1500])
    result, out = run_import(cli, tmp_path, bad, "sb3")
    assert result.exit_code == 2 and "broken.zip" in result.output and "not a readable zip" in result.output
    assert not out.exists()


def test_import_refuses_what_only_unpickling_could_read(cli, sb3_models, tmp_path):
    """A policy.pth of pickled modules, and policy_kwargs naming a class of the user's code."""
    pickled = tmp_path / "pickled.zip"
    with zipfile.ZipFile(sb3_models["td3"]) as src, zipfile.ZipFile(pickled, "w") as dst:
        for item in src.namelist():
            if item != "policy.pth":
                dst.writestr(item, src.read(item))
        import io

        buf = io.BytesIO()
        torch.save({"actor": nn.Linear(17, 6)}, buf)  # an nn.Module object, not tensors
        dst.writestr("policy.pth", buf.getvalue())
    result, out = run_import(cli, tmp_path, pickled, "sb3")
    assert result.exit_code == 2
    assert "pickled.zip" in result.output and "only unpickling" in result.output and not out.exists()

    class MyExtractor(sb3.common.torch_layers.FlattenExtractor):
        pass

    custom = sb3.TD3(
        "MlpPolicy",
        scalar_env(0),
        learning_starts=1000,
        policy_kwargs={"features_extractor_class": MyExtractor},
        device="cpu",
    )
    custom.save(tmp_path / "custom.zip")
    result, out = run_import(cli, tmp_path, tmp_path / "custom.zip", "sb3")
    assert result.exit_code == 2
    assert "custom.zip" in result.output and "MyExtractor" in result.output and "unpickling" in result.output


def test_import_refuses_an_sb3_replay_buffer(cli, sb3_models, tmp_path):
    model = sb3.TD3.load(sb3_models["td3"], env=scalar_env(0), device="cpu")
    model.learn(60, reset_num_timesteps=False)  # fills a (short) replay buffer
    model.save_replay_buffer(tmp_path / "replay.pkl")
    result, out = run_import(cli, tmp_path, sb3_models["td3"], "sb3", buffer=tmp_path / "replay.pkl")
    assert result.exit_code == 2
    assert "replay.pkl" in result.output and "scalar reward" in result.output and not out.exists()


def test_import_takes_a_buffer_in_the_project_format(cli, sb3_models, tmp_path):
    first, out0 = run_import(cli, tmp_path, sb3_models["td3"], "sb3")
    assert first.exit_code == 0, first.output
    result, out1 = run_import(cli, tmp_path, sb3_models["td3"], "sb3", objective=1, buffer=out0 / "buffer.zarr")
    assert result.exit_code == 0, result.output
    a, _ = load_buffer(out0 / "buffer.zarr")
    b, attrs = load_buffer(out1 / "buffer.zarr")
    assert attrs["objective"] == 1 and attrs["collection_frames"] == 0
    # the collection's params are no input of a buffer handed in
    assert load_policy(out1 / "policy.pt")[1]["params"]["import_specialists"] == {}
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])


def test_import_refuses_bounds_of_another_env(cli, spec, tmp_path):
    low, high = 2 * np.array(spec.action_low), 2 * np.array(spec.action_high)
    path = tmp_path / "wide.cleanrl_model"
    torch.save((CleanRLTD3Actor(spec.obs_dim, spec.act_dim, low, high).state_dict(),), path)
    with pytest.raises(ArtifactError, match=r"wide.cleanrl_model: action bounds low"):
        read_policy(path, "cleanrl", spec)


# -- export ---------------------------------------------------------------------------------------


def tiny_population(tmp_path: Path, spec, with_scripted: Path | None = None, with_program: Path | None = None) -> Path:
    torch.manual_seed(2)
    meta = {
        "env_id": ENV,
        "obs_dim": spec.obs_dim,
        "act_dim": spec.act_dim,
        "n_objectives": 2,
        "action_low": list(spec.action_low),
        "action_high": list(spec.action_high),
        "seed": 0,
        "method": "mapex_td3",
        "params": {},
    }
    members = []
    for i, ret in enumerate([[10.0, -50.0], [0.0, -5.0], [5.0, -60.0], [6.0, -20.0]]):
        actor = Actor(spec.obs_dim, spec.act_dim, [8, 8], spec.action_low, spec.action_high)
        origin = "specialist" if i < 2 else "child"
        state = {k: v.clone() for k, v in actor.state_dict().items()}
        if with_scripted is not None and i == 1:
            state = ScriptedActor.from_bytes(with_scripted.read_bytes()).state_dict()
        if with_program is not None and i == 1:
            state = ExportedActor.from_bytes(with_program.read_bytes()).state_dict()
        members.append(
            Member(
                origin,
                i if origin == "specialist" else None,
                0 if origin == "specialist" else 1,
                [] if origin == "specialist" else [0, 1],
                None if origin == "specialist" else [0.6, 0.8],
                ret,
                [0.0, 0.0],
                1,
                i,
                [] if i == 1 and (with_scripted or with_program) is not None else [8, 8],
                state,
                "policy" if origin == "specialist" else None,
            )
        )
    path = tmp_path / "population.pt"
    save_population(path, members, meta)
    return path


def fake_evaluation(tmp_path: Path, population: Path) -> Path:
    """evaluate's outputs for `population` with re-evaluated returns = extraction-time ones."""
    from pipeline.evaluation.episodes import EvalResult
    from stages.evaluate import evaluated_csv

    members, meta = load_population(population)
    spread = np.array([1.0, 2.0])  # two episodes at mean -/+ spread: std = spread
    results = [EvalResult(np.stack([np.array(m.returns) - spread, np.array(m.returns) + spread]), 0) for m in members]
    out = tmp_path / "evaluated"
    out.mkdir()
    (out / "evaluated.csv").write_text(evaluated_csv(members, results))
    record = {"env_id": ENV, "method": meta["method"], "seed": 0, "episodes": 1, "population": len(members)}
    record |= {"env_samples_evaluation": 0, "max_episode_steps": STEPS}
    (out / "evaluation.json").write_text(json.dumps(record))
    return out


def test_export_writes_the_front_as_torchscript_that_loads_without_the_project(cli, spec, tmp_path):
    script, module = scripted_file(tmp_path, spec)
    population = tiny_population(tmp_path, spec, with_scripted=script)
    evaluated = fake_evaluation(tmp_path, population)
    out = tmp_path / "export"
    result = cli(
        "export", "--population", population, "--evaluated", evaluated, "--out", out, "--params", params_file(tmp_path)
    )
    assert result.exit_code == 0, result.output
    doc = json.loads((out / "front.json").read_text())
    assert [p["id"] for p in doc["policies"]] == [1, 3, 0]  # member 2 is dominated by 0; sorted by obj0
    assert doc["policies"][1]["parents"] == [0, 1] and doc["policies"][1]["returns_std"] == [1.0, 2.0]
    assert (out / "front.csv").read_text().splitlines()[0].startswith("id,file,onnx_file,pt2_file,origin")
    # none for the TorchScript specialist (member 1): torch.export does not take TorchScript
    assert [p["pt2_file"] for p in doc["policies"]] == [None, "member_0003.pt2", "member_0000.pt2"]
    members, meta = load_population(population)
    obs = random_obs(20)
    np.save(tmp_path / "obs.npy", obs)
    # a fresh interpreter in which this project cannot be imported
    code = (
        "import sys, json; sys.modules['pipeline'] = None; sys.modules['stages'] = None\n"
        "import numpy as np, torch\n"
        f"out, obs = {str(out)!r}, torch.from_numpy(np.load({str(tmp_path / 'obs.npy')!r}))\n"
        "doc = json.load(open(out + '/front.json'))\n"
        "res = {p['id']: torch.jit.load(out + '/' + p['file'])(obs).tolist() for p in doc['policies']}\n"
        "pt2 = {p['id']: torch.export.load(out + '/' + p['pt2_file']).module()(obs).tolist()\n"
        "       for p in doc['policies'] if p['pt2_file']}\n"
        "print(json.dumps({'ts': res, 'pt2': pt2}))\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    both = json.loads(r.stdout)
    got = both["ts"]
    assert sorted(both["pt2"]) == ["0", "3"]
    for pid, actions in [*got.items(), *both["pt2"].items()]:
        with torch.no_grad():
            want = member_actor(members[int(pid)], meta)(torch.from_numpy(obs)).numpy()
        np.testing.assert_allclose(np.array(actions), want, atol=1e-6, rtol=0)
    with torch.no_grad():  # the TorchScript specialist is exported as the user's own file
        np.testing.assert_allclose(np.array(got["1"]), module(torch.from_numpy(obs)).numpy(), atol=1e-6, rtol=0)


def test_export_writes_onnx_when_installed(cli, spec, tmp_path):
    ort = pytest.importorskip("onnxruntime")
    script, _ = scripted_file(tmp_path, spec)
    population = tiny_population(tmp_path, spec, with_scripted=script)  # a TorchScript member too
    evaluated = fake_evaluation(tmp_path, population)
    out = tmp_path / "export"
    args = ["export", "--population", population, "--evaluated", evaluated, "--out", out, "--onnx", "yes"]
    result = cli(*args, "--params", params_file(tmp_path))
    assert result.exit_code == 0, result.output
    members, meta = load_population(population)
    obs = random_obs(10)
    for p in json.loads((out / "front.json").read_text())["policies"]:
        session = ort.InferenceSession(str(out / p["onnx_file"]))
        with torch.no_grad():
            want = member_actor(members[p["id"]], meta)(torch.from_numpy(obs)).numpy()
        np.testing.assert_allclose(session.run(None, {"obs": obs})[0], want, atol=1e-5, rtol=0)


# -- the pipeline: one dvc repro from imported specialists to the report --------------------------


@pytest.mark.slow  # two dvc repro chains (all imported, then mixed sources): slow keeps `make test` within 8 min
def test_dvc_repro_from_imported_specialists(sb3_models, tmp_path):
    """import_specialist -> fit_critics -> mapex_posthoc_imported, and warmup_only_imported (no critics) ->
    evaluate -> score -> export -> report on a tiny preset, whose report pairs MAPEX-PostHoc with
    warm-up only in a verdict, nothing trained here. Then the paper's case, mixed sources: the
    energy entry dropped, objective 1's slot is a TD3 specialist trained here (stage
    train_specialist_imported) beside the imported speed specialist; its chain runs and the speed
    one's import and fit do not, both slots get post-hoc critics and say where they came from, and
    the report names the sources and gives the verdict. A td3 change reaches only the slot trained
    here; a new speed model only the import."""
    import re
    import shutil

    import yaml
    from support.tiny_params import TINY_CHAIN as TINY
    from support.tiny_params import save_params, with_lists

    root = Path(__file__).resolve().parents[1]
    bin_dir = Path(sys.executable).parent
    repo = tmp_path / "repo"
    for name in ("pipeline", "stages"):
        shutil.copytree(root / name, repo / name, ignore=shutil.ignore_patterns("__pycache__"))
    (repo / "presets").mkdir()  # the score stage's table of reference points (a DVC dep)
    shutil.copy(root / "presets" / "envs.yaml", repo / "presets" / "envs.yaml")
    (repo / "models").mkdir()
    shutil.copy(sb3_models["td3"], repo / "models" / "speed.zip")
    shutil.copy(sb3_models["sac"], repo / "models" / "energy.zip")
    params = with_lists(
        {
            **TINY,
            "methods": ["mapex_posthoc_imported", "warmup_only_imported"],
            "import_specialists": {
                "policies": [
                    {"objective": 0, "file": "models/speed.zip", "format": "sb3"},
                    {"objective": 1, "file": "models/energy.zip", "format": "sb3"},
                ],
                "collect_rows": 200,
                "exploration_noise": 0.1,
            },
            "export": {"methods": ["mapex_posthoc_imported"]},
        }
    )
    save_params(repo / "params.yaml", params, sort_keys=False)
    from pipeline.params.plan import write_plan

    write_plan(params, repo / "params.yaml", repo)  # `mapex plan`
    (repo / ".gitignore").write_text("/data/\n__pycache__/\nMUJOCO_LOG.TXT\n")
    env = {**os.environ, "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}", "PYTHONPATH": str(repo)}

    def run(*cmd: str) -> str:
        r = subprocess.run(list(cmd), cwd=repo, env=env, capture_output=True, text=True)
        assert r.returncode == 0, f"{' '.join(cmd)} failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
        return r.stdout + r.stderr

    for cmd in (["git", "init", "-q"], ["git", "config", "user.email", "t@e.com"], ["git", "config", "user.name", "t"]):
        run(*cmd)
    run(str(bin_dir / "dvc"), "init", "-q")
    run("git", "add", "-A")
    run("git", "commit", "-qm", "imported")
    out = run(str(bin_dir / "dvc"), "repro")
    ran = set(re.findall(r"Running stage '([^']+)'", out))
    assert {
        "import_specialist@0-policy0",
        "import_specialist@0-policy1",
        "mapex_posthoc_imported@0",
        "warmup_only_imported@0",
        "report",
    } <= ran
    assert not any(s.startswith("train_specialist") for s in ran)  # nothing trained here
    report = (repo / "data" / "report" / "report.md").read_text()
    assert "MAPEX-PostHoc (imported)" in report and "collecting the imported specialists' buffers" in report
    # the paired verdict an imported run gives, as a TD3 run does (warm-up only reads no critics)
    assert "No pair of comparable methods was run" not in report
    assert re.search(
        r"the advantage-weighted phase \(MAPEX-PostHoc, imported\) (beat|lost to|tied with) warm-up only \(imported\)",
        report,
    ), report
    _, warm = load_population(repo / "data/fronts/warmup_only_imported/seed0/population.pt")
    assert warm["params"]["critics"] == "none" and warm["params"]["extract"]["epochs"] == 0
    doc = json.loads((repo / "data/export/mapex_posthoc_imported/seed0/front.json").read_text())
    assert doc["policies"] and all(
        (repo / "data/export/mapex_posthoc_imported/seed0" / p["file"]).is_file() for p in doc["policies"]
    )
    assert "specialists of the imported kind" not in report  # all imported: nothing new to say

    # mixed sources: no energy entry, so objective 1 is trained here by TD3; the speed chain stays cached
    params["import_specialists"]["policies"] = params["import_specialists"]["policies"][:1]
    params = with_lists(params)
    assert params["import_train"] == [1] and params["td3_seeds"] == []
    save_params(repo / "params.yaml", params, sort_keys=False)
    write_plan(params, repo / "params.yaml", repo)  # `mapex plan`
    again = set(re.findall(r"Running stage '([^']+)'", run(str(bin_dir / "dvc"), "repro")))
    assert {
        "train_specialist_imported@0-1",
        "fit_critics@0-imported-1",
        "mapex_posthoc_imported@0",
        "warmup_only_imported@0",
        "report",
    } <= again
    assert "import_specialist@0-policy0" not in again and "fit_critics@0-imported-0" not in again
    assert not any(s.startswith("train_specialist@") for s in again)  # no TD3 specialist of objective 0
    slots = repo / "data" / "specialists" / "imported" / "seed0"
    _, speed = load_policy(slots / "obj0" / "policy.pt")
    _, energy, target = load_policy(slots / "obj1" / "policy.pt", target=True)
    assert speed["source"]["format"] == "sb3" and speed["source"]["file"] == "speed.zip"
    assert (
        energy["source"] == {"trained": "td3"} and target is not None and not (slots / "obj1" / "collect.csv").exists()
    )
    assert energy["params"]["td3"]["hidden_sizes"] == params["td3"]["hidden_sizes"]  # trained with td3's settings
    for k in (0, 1):  # every slot judged by critics of one kind, fitted on its own buffer
        cmeta = torch.load(repo / "data/posthoc/imported/seed0" / f"obj{k}" / "critics.pt", weights_only=True)["meta"]
        assert cmeta["source"] == "posthoc" and cmeta["buffer_objective"] == k
    members, meta = load_population(repo / "data/fronts/mapex_posthoc_imported/seed0/population.pt")
    assert any(m.origin == "child" for m in members)
    assert meta["specialist_sources"] == [
        {"objective": 0, "imported": {"format": "sb3", "algorithm": "td3", "file": "speed.zip"}},
        {"objective": 1, "trained": "td3", "total_steps": params["train_specialist"]["total_steps"]},
    ]
    assert (repo / "data/score/mapex_posthoc_imported/seed0/front.csv").read_text().count("\n") > 1
    report = (repo / "data" / "report" / "report.md").read_text()
    assert re.search(
        r"- specialists of the imported kind: objectives imported: 0 \(x velocity: sb3 td3, file speed\.zip\); "
        r"trained here: 1 \(energy[^:]*: TD3, 300 steps",
        report,
    ), report
    assert re.search(
        r"the advantage-weighted phase \(MAPEX-PostHoc, imported\) (beat|lost to|tied with) warm-up only \(imported\)",
        report,
    ), report

    # what reruns: a td3 change reaches the slot trained here, not the import; a new speed model, the import
    changed = yaml.safe_load((repo / "params.yaml").read_text())
    changed["td3"]["batch_size"] = 16
    save_params(repo / "params.yaml", changed, sort_keys=False)
    status = run(str(bin_dir / "dvc"), "status")
    assert "train_specialist_imported@0-1" in status and "import_specialist@0-policy0" not in status
    save_params(repo / "params.yaml", params, sort_keys=False)
    shutil.copy(sb3_models["sac"], repo / "models" / "speed.zip")
    status = run(str(bin_dir / "dvc"), "status")
    assert "import_specialist@0-policy0" in status and "train_specialist_imported@0-1" not in status
