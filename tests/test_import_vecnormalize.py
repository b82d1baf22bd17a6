"""Models trained under SB3's VecNormalize(norm_obs=True), imported with their statistics: the
actions on raw observations equal SB3's on the normalised ones, through the stage, the slot's
artifacts, the exports (TorchScript and .pt2, loaded without this project) and DVC.

A real SB3 TD3 is trained here for 200 steps (100 gradient steps) under VecNormalize.
"""

from __future__ import annotations

import json
import os
import pickle
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from pipeline.core.artifacts import ArtifactError
from pipeline.core.checkpoint import load_policy
from pipeline.core.envs import env_spec, make_env
from pipeline.core.nets import NormalizedActor
from pipeline.core.population import Member, load_population, member_actor, save_population
from pipeline.interop.readers import file_sha256, input_scale_warning, read_policy

pytestmark = pytest.mark.integration  # SB3 training, a fresh interpreter, dvc repro

sb3 = pytest.importorskip("stable_baselines3")
from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize  # noqa: E402

ENV = "mo-halfcheetah-v5"
STEPS = 40


@pytest.fixture(scope="module")
def spec():
    env = make_env(ENV, STEPS)
    s = env_spec(env, ENV, STEPS)
    env.close()
    return s


def scalar_venv():
    import mo_gymnasium as mo
    from mo_gymnasium.wrappers import LinearReward

    weight = np.array([1.0, 0.0], dtype=np.float32)  # objective 0: x velocity
    return DummyVecEnv([lambda: LinearReward(mo.make(ENV, max_episode_steps=STEPS), weight=weight)])


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> dict[str, Path]:
    """A TD3 trained under VecNormalize(norm_obs=True) (model.zip, vecnormalize.pkl saved
    together, as rl-zoo3 does), and one trained on raw observations (plain.zip)."""
    root = tmp_path_factory.mktemp("vecnorm")
    venv = VecNormalize(scalar_venv(), norm_obs=True)
    model = sb3.TD3("MlpPolicy", venv, learning_starts=100, policy_kwargs={"net_arch": [32, 24]}, seed=0, device="cpu")
    model.learn(200)
    model.save(root / "model.zip")
    venv.save(str(root / "vecnormalize.pkl"))
    plain = sb3.TD3(
        "MlpPolicy", scalar_venv(), learning_starts=100, policy_kwargs={"net_arch": [32, 24]}, seed=1, device="cpu"
    )
    plain.learn(120)
    plain.save(root / "plain.zip")
    return {"model": root / "model.zip", "stats": root / "vecnormalize.pkl", "plain": root / "plain.zip"}


def raw_obs(n: int = 100, seed: int = 0) -> np.ndarray:
    """Raw observations at HalfCheetah's scale (velocities of several units)."""
    return (np.random.default_rng(seed).normal(size=(n, 17)) * 3).astype(np.float32)


def sb3_actions(trained: dict[str, Path], obs: np.ndarray) -> np.ndarray:
    """SB3's own: its VecNormalize loaded by SB3 normalises, its policy predicts."""
    vn = VecNormalize.load(str(trained["stats"]), scalar_venv())
    model = sb3.TD3.load(trained["model"], device="cpu")
    return model.predict(vn.normalize_obs(obs), deterministic=True)[0]


def test_imported_actions_equal_sb3_on_raw_observations(trained, spec):
    obs = raw_obs()
    want = sb3_actions(trained, obs)
    imported = read_policy(trained["model"], "sb3", spec, trained["stats"])
    assert imported.architecture == "normalized_mlp" and isinstance(imported.actor, NormalizedActor)
    assert imported.warnings == ()  # the statistics turn its last raw observation into what it saw
    with torch.no_grad():
        got = imported.actor(torch.from_numpy(obs)).numpy()
    np.testing.assert_allclose(got, want, atol=1e-6, rtol=0)
    # without them: other actions, and on the env's raw observations a warning that says why
    bare = read_policy(trained["model"], "sb3", spec)
    with torch.no_grad():
        assert np.abs(bare.actor(torch.from_numpy(obs)).numpy() - want).max() > 0.05
    env_obs = env_observations()
    line = input_scale_warning(trained["model"], bare.input_scales, env_obs, normalized=False)
    assert line and line.startswith(f"{trained['model']}: warning: likely trained on normalised observations")
    assert "\n" not in line and "import_specialists.policies[].normalize" in line
    assert input_scale_warning(trained["model"], imported.input_scales, env_obs, normalized=True) is None
    # a model trained on raw observations gives none
    plain = read_policy(trained["plain"], "sb3", spec)
    assert plain.warnings == () and input_scale_warning(trained["plain"], plain.input_scales, env_obs, False) is None


def env_observations(n: int = 200) -> np.ndarray:
    """Raw observations of the MO env under random actions."""
    env = make_env(ENV, STEPS)
    env.action_space.seed(0)
    obs, rows = env.reset(seed=0)[0], []
    for _ in range(n):
        obs, _, terminated, truncated, _ = env.step(env.action_space.sample())
        rows.append(obs)
        if terminated or truncated:
            obs = env.reset()[0]
    env.close()
    return np.asarray(rows, np.float32)


def test_statistics_of_another_point_of_training_give_a_warning(trained, spec, tmp_path):
    vn = VecNormalize.load(str(trained["stats"]), scalar_venv())
    vn.obs_rms.mean = vn.obs_rms.mean + 0.5
    vn.save(str(tmp_path / "other.pkl"))
    imported = read_policy(trained["model"], "sb3", spec, tmp_path / "other.pkl")
    assert len(imported.warnings) == 1 and "does not turn the model's last raw observation" in imported.warnings[0]
    # norm_obs false: the statistics are recorded and the actor is left as it is
    off = VecNormalize(scalar_venv(), norm_obs=False)
    off.save(str(tmp_path / "off.pkl"))
    imported = read_policy(trained["model"], "sb3", spec, tmp_path / "off.pkl")
    assert imported.architecture == "mlp" and imported.source["normalize"]["norm_obs"] is False


class RunsCode:
    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def params_file(tmp_path: Path, rows: int = 40) -> Path:
    p = {
        "env": {"id": ENV, "max_episode_steps": STEPS},
        "seeds": [0],
        "methods": ["mapex_td3"],
        "import_specialists": {"collect_rows": rows},
    }
    path = tmp_path / "params.yaml"
    path.write_text(yaml.safe_dump(p))
    return path


def run_import(cli, tmp_path: Path, model: Path, normalize: Path | str, rows: int = 40, out: str = "slot"):
    out = tmp_path / out / "obj0"
    args = ["import-specialist", "--objective", 0, "--file", model, "--format", "sb3", "--out", out]
    return cli(*args, "--normalize", normalize, "--params", params_file(tmp_path, rows)), out


def test_the_stage_warns_when_a_normalised_model_comes_without_statistics(cli, trained, tmp_path):
    result, _ = run_import(cli, tmp_path, trained["model"], "none", rows=200)
    assert result.exit_code == 0, result.output  # a warning, not a refusal
    warned = [line for line in result.stderr.splitlines() if "warning: likely trained on normalised" in line]
    assert len(warned) == 1 and warned[0].startswith(str(trained["model"])), result.stderr
    result, _ = run_import(cli, tmp_path, trained["plain"], "none", rows=200, out="plain")
    assert result.exit_code == 0, result.output
    assert "warning" not in result.stderr


def test_a_statistics_file_that_would_run_code_is_refused_by_the_stage(cli, trained, tmp_path):
    marker = tmp_path / "ran"
    vn = VecNormalize.load(str(trained["stats"]), scalar_venv())
    vn.note = RunsCode(marker)  # a real VecNormalize, with one attribute that runs code when unpickled
    bad = tmp_path / "vecnormalize.pkl"
    vn.save(str(bad))
    result, out = run_import(cli, tmp_path, trained["model"], bad)
    assert result.exit_code == 2, result.output
    errors = [line for line in result.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and str(bad) in errors[0] and f"{os.system.__module__}.system" in errors[0], errors
    assert not marker.exists() and not out.exists()


def fake_evaluated(tmp_path: Path, population: Path) -> Path:
    """evaluate's outputs for `population`, returns as at extraction."""
    from pipeline.evaluation.episodes import EvalResult
    from stages.evaluate import evaluated_csv

    members, meta = load_population(population)
    results = [EvalResult(np.stack([np.array(m.returns)] * 2), 0) for m in members]
    out = tmp_path / "evaluated"
    out.mkdir()
    (out / "evaluated.csv").write_text(evaluated_csv(members, results))
    record = {"env_id": ENV, "method": meta["method"], "seed": 0, "episodes": 2, "population": len(members)}
    (out / "evaluation.json").write_text(json.dumps(record | {"env_samples_evaluation": 0, "max_episode_steps": STEPS}))
    return out


def test_the_stage_bakes_the_statistics_in_and_the_exports_take_raw_observations(cli, trained, spec, tmp_path):
    result, slot = run_import(cli, tmp_path, trained["model"], trained["stats"])
    assert result.exit_code == 0, result.output
    assert "observation statistics of" in result.stderr and "warning" not in result.stderr
    actor, meta = load_policy(slot / "policy.pt")
    assert meta["architecture"] == "normalized_mlp" and meta["hidden_sizes"] == [32, 24]
    assert meta["source"]["normalize"] == {
        "file": str(trained["stats"]),
        "sha256": file_sha256(trained["stats"]),
        "norm_obs": True,
        "norm_reward": True,
        "mean_shape": [17],
        "var_shape": [17],
        "epsilon": 1e-8,
        "clip_obs": 10.0,
    }
    obs = raw_obs(64, seed=3)
    want = sb3_actions(trained, obs)
    with torch.no_grad():
        np.testing.assert_allclose(actor(torch.from_numpy(obs)).numpy(), want, atol=1e-6, rtol=0)

    # a front holding it (as extraction stores a starting policy) and a child: exported
    pop_meta = {k: meta[k] for k in ("env_id", "obs_dim", "act_dim", "n_objectives", "action_low", "action_high")}
    pop_meta |= {"seed": 0, "method": "mapex_posthoc_imported", "params": {}}
    child = NormalizedActor(17, 6, [32, 24], meta["action_low"], meta["action_high"])  # any second member
    state = {k: v.clone() for k, v in actor.state_dict().items()}
    members = [
        Member("specialist", 0, 0, [], None, [10.0, -50.0], [0.0, 0.0], 1, 0, [32, 24], state, "policy"),
        Member("child", None, 1, [0], [1.0, 0.0], [0.0, -5.0], [0.0, 0.0], 1, 1, [32, 24], child.state_dict()),
    ]
    save_population(tmp_path / "population.pt", members, pop_meta)
    assert type(member_actor(members[0], pop_meta)) is NormalizedActor
    evaluated = fake_evaluated(tmp_path, tmp_path / "population.pt")
    export = tmp_path / "export"
    args = ["export", "--population", tmp_path / "population.pt", "--evaluated", evaluated, "--out", export]
    result = cli(*args, "--onnx", "no", "--params", params_file(tmp_path))
    assert result.exit_code == 0, result.output
    doc = json.loads((export / "front.json").read_text())
    first = next(p for p in doc["policies"] if p["id"] == 0)
    np.save(tmp_path / "obs.npy", obs)
    code = (  # a fresh interpreter in which this project cannot be imported: raw observations in
        "import sys, json; sys.modules['pipeline'] = None; sys.modules['stages'] = None\n"
        "import numpy as np, torch\n"
        f"obs = torch.from_numpy(np.load({str(tmp_path / 'obs.npy')!r}))\n"
        f"ts = torch.jit.load({str(export / first['file'])!r})(obs)\n"
        f"pt2 = torch.export.load({str(export / first['pt2_file'])!r}).module()(obs)\n"
        "print(json.dumps({'ts': ts.tolist(), 'pt2': pt2.tolist()}))\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    for kind, actions in json.loads(r.stdout).items():
        np.testing.assert_allclose(np.array(actions), want, atol=1e-6, rtol=0, err_msg=kind)


@pytest.mark.slow  # a dvc repro of two imports: slow keeps `make test` within 8 min
def test_dvc_tracks_the_statistics_named_or_found_in_rl_zoo3_layout(trained, tmp_path):
    """Objective 0 names its statistics; objective 1's model sits in an rl-zoo3 run folder with
    its statistics where rl-zoo3 saves them. `mapex plan` finds them, both imports bake
    them in, and a change to one statistics file reruns that import alone."""
    import shutil

    from support.dvc_repo import DVC, make_repo, ran, run
    from support.tiny_params import TINY_CHAIN

    from pipeline.params.common import DERIVED_KEYS

    repo = tmp_path / "repo"
    (repo / "models").mkdir(parents=True)
    shutil.copy(trained["model"], repo / "models" / "speed.zip")
    shutil.copy(trained["stats"], repo / "models" / "speed_vecnormalize.pkl")
    zoo = repo / "logs" / "td3" / "mo-halfcheetah-v5_1"
    (zoo / "mo-halfcheetah-v5").mkdir(parents=True)
    shutil.copy(trained["model"], zoo / "mo-halfcheetah-v5.zip")
    shutil.copy(trained["stats"], zoo / "mo-halfcheetah-v5" / "vecnormalize.pkl")
    policies = [
        {"objective": 0, "file": "models/speed.zip", "format": "sb3", "normalize": "models/speed_vecnormalize.pkl"},
        {"objective": 1, "file": "logs/td3/mo-halfcheetah-v5_1/mo-halfcheetah-v5.zip", "format": "sb3"},
    ]
    params = {k: v for k, v in TINY_CHAIN.items() if k not in DERIVED_KEYS}  # the plan derives them
    params |= {"methods": ["mapex_posthoc_imported"]}
    params["import_specialists"] = {"policies": policies, "collect_rows": 40, "exploration_noise": 0.1}
    make_repo(repo, params)
    run([str(Path(sys.executable).parent / "mapex"), "plan"], repo)  # paths from the repository root
    found = "logs/td3/mo-halfcheetah-v5_1/mo-halfcheetah-v5/vecnormalize.pkl"
    planned = yaml.safe_load((repo / "dvc.yaml").read_text())["stages"]["import_specialist"]["matrix"]
    synced = planned["policy"]  # the run list, as the plan writes it into the matrix
    assert [p["normalize"] for p in synced] == ["models/speed_vecnormalize.pkl", found]
    run(["git", "add", "-A"], repo)
    run(["git", "commit", "-qm", "planned"], repo)
    out = run([DVC, "repro", "import_specialist"], repo)
    assert ran(out) == {"import_specialist"} and out.count("observation statistics of") == 2
    for k, stats in ((0, "models/speed_vecnormalize.pkl"), (1, found)):
        _, meta = load_policy(repo / f"data/specialists/imported/seed0/obj{k}/policy.pt")
        assert meta["architecture"] == "normalized_mlp" and meta["source"]["normalize"]["file"] == stats
    # new statistics for objective 1: DVC sees its import as changed, and objective 0's not
    vn = VecNormalize.load(str(repo / found), scalar_venv())
    vn.obs_rms.var = vn.obs_rms.var * 2
    with open(repo / found, "wb") as f:
        pickle.dump(vn, f)
    status = run([DVC, "status", "import_specialist"], repo)
    changed = set(re.findall(r"^(import_specialist@\S+):", status, flags=re.M))
    assert changed == {"import_specialist@0-policy1"}, status


def test_a_model_that_does_not_fit_the_statistics_is_refused(trained, spec, tmp_path):
    vn = VecNormalize.load(str(trained["stats"]), scalar_venv())
    vn.obs_rms.mean, vn.obs_rms.var = vn.obs_rms.mean[:5], vn.obs_rms.var[:5]
    vn.save(str(tmp_path / "short.pkl"))
    with pytest.raises(ArtifactError, match=r"statistics of 5-d observations; env mo-halfcheetah-v5 has 17"):
        read_policy(trained["model"], "sb3", spec, tmp_path / "short.pkl")
