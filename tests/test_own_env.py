"""Your own env: a single-objective Gymnasium env made multi-objective from its reward terms
(env.reward_terms), Gymnasium's module:EnvId ids, the one-line refusals before any work, and the
whole pipeline through DVC on the project's own non-MuJoCo env (examples/pointrunner), with clips."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from support.dvc_repo import BIN, ROOT, make_repo, ran, run
from support.tiny_params import TINY_CHAIN, merge, save_params

from pipeline.core.envs import EnvError, env_spec, make_env
from pipeline.evaluation.preflight import preflight
from pipeline.params import EnvParams, ParamsError
from pipeline.params.common import RewardTerm

RUNNER = "examples.pointrunner:PointRunner-v0"
RUNNER_ENV = {
    "id": RUNNER,
    "max_episode_steps": 30,
    "reward_terms": [{"info": "reward_forward", "name": "speed"}, {"info": "reward_ctrl", "name": "energy"}],
    "reference_point": [-10.0, -100.0],
    "objective_names": None,
}


def test_reward_terms_make_a_gymnasium_env_multi_objective():
    """Gymnasium's own HalfCheetah-v5 (one scalar reward) with two info terms: a vector reward,
    each entry the term's info value times its scale, and names from the terms."""
    env_p = EnvParams(
        id="HalfCheetah-v5",
        max_episode_steps=20,
        reward_terms=[{"info": "reward_forward", "name": "speed"}, {"info": "reward_ctrl", "scale": 2.0}],
    )
    assert env_p.objective_names == ["speed", "reward_ctrl"]
    env = make_env(env_p.id, env_p.max_episode_steps, env_p.reward_terms)
    try:
        spec = env_spec(env, env_p.id, env_p.max_episode_steps)
        assert (spec.n_objectives, spec.obs_dim, spec.act_dim) == (2, 17, 6)
        env.reset(seed=3)
        action = np.full(6, 0.5, dtype=np.float32)
        _, reward, _, _, info = env.step(action)
        assert reward.shape == (2,)
        assert reward[0] == pytest.approx(info["reward_forward"])
        assert reward[1] == pytest.approx(2.0 * info["reward_ctrl"])
    finally:
        env.close()


def test_a_function_term_and_a_module_env_id(tmp_path, monkeypatch):
    """A term that names module:function (the user's own code) and an env id in Gymnasium's
    module:EnvId form, both imported from the working directory, as a stage runs them."""
    (tmp_path / "myterms.py").write_text(
        "def upright(obs, action, reward, next_obs, info):\n    return float(next_obs[2]) * 10.0\n"
    )
    monkeypatch.chdir(tmp_path)
    shutil.copytree(ROOT / "examples", tmp_path / "examples", ignore=shutil.ignore_patterns("__pycache__"))
    sys.modules.pop("examples.pointrunner", None)
    sys.modules.pop("examples", None)
    terms = [RewardTerm(info="reward_forward"), RewardTerm(function="myterms:upright", name="upright")]
    env = make_env(RUNNER, 10, terms)
    try:
        obs, _ = env.reset(seed=0)
        nxt, reward, *_ = env.step(np.array([1.0, 0.0], dtype=np.float32))
        assert reward[1] == pytest.approx(10.0 * nxt[2])
        assert env.observation_space.shape == (3,)
    finally:
        env.close()


def test_bad_env_params_are_refused_in_one_line_before_any_work(tmp_path):
    """Each of what a later stage would refuse is said when the run is planned (preflight, which
    `mapex plan` runs), in one line naming the key."""
    cases = [
        ({**RUNNER_ENV, "reward_terms": [{"info": "reward_forward"}, {"info": "speed"}]}, "info key 'speed'"),
        ({**RUNNER_ENV, "reward_terms": None}, "env.reward_terms"),
        ({**RUNNER_ENV, "id": "no-such-env-v0"}, "cannot build it"),
        ({**RUNNER_ENV, "id": "no_such_module:Env-v0"}, "cannot import module"),
        ({**RUNNER_ENV, "id": "Pendulum-v1", "reward_terms": None}, "env.reward_terms"),  # scalar reward
        ({**RUNNER_ENV, "id": "CartPole-v1", "reward_terms": None}, "expected a continuous Box"),
        ({**RUNNER_ENV, "reference_point": [-1.0, -1.0, -1.0]}, "has 3 values"),
        ({**RUNNER_ENV, "reward_terms": None, "id": "mo-halfcheetah-v5", "objective_names": ["a"]}, "1 names"),
    ]
    for env, expected in cases:
        try:
            preflight(EnvParams.model_validate(env), tmp_path / "params.yaml")
        except (EnvError, ParamsError) as exc:
            line = str(exc)
            assert expected in line and "\n" not in line, (env, line)
        else:
            pytest.fail(f"{env}: accepted")
    # an env presets/envs.yaml does not list gets a derived point (auto), planned without error
    assert preflight(EnvParams.model_validate({**RUNNER_ENV, "reference_point": None}), tmp_path).n_objectives == 2
    with pytest.raises(ValueError, match="objective_names has 1 names, reward_terms 2 terms"):
        EnvParams.model_validate({**RUNNER_ENV, "objective_names": ["a"]})
    with pytest.raises(ValueError, match="exactly one of info"):
        RewardTerm(info="a", function="m:f")


def _cli(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}", "PYTHONPATH": str(ROOT)}
    return subprocess.run([str(BIN / "mapex"), *args], cwd=cwd, env=env, capture_output=True, text=True)


def test_a_bad_objective_key_stops_planning_and_training_in_one_line(tmp_path):
    """`mapex plan` (what `make repro` runs first) and the training stage both stop in one line
    on an info key the env does not return, and nothing is trained."""
    shutil.copytree(ROOT / "examples", tmp_path / "examples", ignore=shutil.ignore_patterns("__pycache__"))
    params = merge(TINY_CHAIN, {"env": {**RUNNER_ENV, "reward_terms": [{"info": "reward_forward"}, {"info": "nope"}]}})
    save_params(tmp_path / "params.yaml", params)
    for args in (["plan"], ["train-specialist", "--seed", "0", "--out", "data/specialists/td3/seed0"]):
        r = _cli(*args, cwd=tmp_path)
        assert r.returncode == 2, (args, r.stdout, r.stderr)
        lines = [line for line in r.stderr.splitlines() if line.strip()]
        assert lines[-1].startswith("error: ") and "info key 'nope'" in lines[-1], r.stderr
        assert "Traceback" not in r.stderr
    assert not (tmp_path / "data").exists()


@pytest.mark.slow  # about 50 s alone: the slow tier (CI runs it) keeps `make test` under 8 minutes
def test_dvc_repro_on_a_non_mujoco_env_reaches_the_report_and_the_explorer_with_clips(tmp_path):
    """The quickstart-sized pipeline on examples/pointrunner (no MuJoCo), objectives from its
    reward terms: specialists, extraction, evaluation, the report with the terms' names, and the
    explorer with a clip of every front member, filmed through the env's own rgb_array."""
    params = merge(
        TINY_CHAIN,
        {
            "env": {**RUNNER_ENV, "reference_point": None},  # not in presets/envs.yaml: auto
            "train_specialist": {"total_steps": 600},
            "td3": {"learning_starts": 150},
            "render": {"methods": ["mapex_td3"], "frames": 6, "every": 5},
        },
    )
    root = make_repo(tmp_path / "repo", params)
    shutil.copytree(ROOT / "examples", root / "examples", ignore=shutil.ignore_patterns("__pycache__"))
    run(["git", "add", "examples"], root)
    run(["git", "commit", "-qm", "the user's env"], root)
    out = run([str(BIN / "dvc"), "repro"], root)
    assert {"train_specialist", "mapex_td3", "evaluate", "score", "render", "report"} <= ran(out)
    report = (root / "data" / "report" / "report.md").read_text()
    assert RUNNER in report and "speed" in report and "energy" in report
    # the point came from the run's own starting policies, and the report says so
    metrics = json.loads((root / "data" / "score" / "mapex_td3" / "seed0" / "metrics.json").read_text())
    assert metrics["reference_point_source"].startswith("auto: derived from this run's 2 starting policies")
    assert "derived from this run's" in report
    index = json.loads((root / "data" / "render" / "index.json").read_text())
    assert index["objectives"] == ["speed", "energy"] and "no_clips" not in index
    front = [p for panel in index["panels"] if panel["method"] == "mapex_td3" for p in panel["points"] if p["on_front"]]
    assert front and all(p["clip"] for p in front)
    clip = root / "data" / "render" / front[0]["clip"]["mp4"]
    assert clip.stat().st_size > 0
    assert (root / "data" / "render" / "explorer.html").is_file()
    # every stage that builds the env tracks the terms: a new scale reruns the specialists
    edited = yaml.safe_load((root / "params.yaml").read_text())
    edited["env"]["reward_terms"][1]["scale"] = 0.5
    save_params(root / "params.yaml", edited)
    from test_dvc_methods import stale_stages

    assert {"train_specialist", "mapex_td3", "evaluate", "render", "report"} <= stale_stages(root)


def test_auto_reference_point_rule_and_where_it_applies(tmp_path):
    """The rule: worst return less 10% of the spread (at least 1% of the worst's magnitude, and 1);
    null takes the table's entry for a listed env and the rule for any other; auto always the rule."""
    from pipeline.evaluation.reference_points import auto_reference_point, resolve_reference_point

    starting = np.array([[200.0, -50.0], [0.0, -0.5]])
    assert auto_reference_point(starting).tolist() == pytest.approx([-20.0, -54.95])
    assert auto_reference_point(np.array([[5.0, 5.0], [5.0, 5.0]])).tolist() == pytest.approx([4.0, 4.0])
    listed = resolve_reference_point(None, "mo-halfcheetah-v5", 2, tmp_path, starting=starting)
    assert listed.point.tolist() == [-100.0, -4500.0] and "auto" not in listed.source
    for given, env_id in ((None, RUNNER), ("auto", "mo-halfcheetah-v5")):
        got = resolve_reference_point(given, env_id, 2, tmp_path, starting=starting)
        assert got.point.tolist() == pytest.approx([-20.0, -54.95]) and got.source.startswith("auto")
    assert EnvParams.model_validate({**RUNNER_ENV, "reference_point": "auto"}).reference_point == "auto"


def test_an_env_that_cannot_be_filmed_gets_the_explorer_without_clips(tmp_path, monkeypatch):
    """render_problem names why an env cannot be filmed (here, one whose render() gives no
    image); stage render then writes the explorer without clips and that line, never fails."""
    from pipeline.evaluation.render import Film, render_problem

    monkeypatch.chdir(ROOT)
    film = Film(RUNNER, 10, 4, 1, None, 64, 64, None, None, -15.0, 90.0, 0, 0, 0, tuple(RUNNER_ENV["reward_terms"]))
    assert render_problem(film) is None
    import examples.pointrunner as pr

    monkeypatch.setattr(pr.PointRunner, "render", lambda self: None)
    line = render_problem(film)
    assert line is not None and "returned nothing" in line and "\n" not in line
