"""Env building: the paper's five envs, the episode cap, and envs that MAPEX cannot use."""

from __future__ import annotations

import re

import numpy as np
import pytest

from pipeline.core.envs import EnvError, env_spec, make_env, objective_names

# (id, obs_dim, act_dim): the paper's v5 MuJoCo envs, all with 2 objectives.
PAPER_ENVS = [
    ("mo-ant-2obj-v5", 105, 8),
    ("mo-hopper-2obj-v5", 11, 3),
    ("mo-swimmer-v5", 8, 2),
    ("mo-walker2d-v5", 17, 6),
    ("mo-halfcheetah-v5", 17, 6),
]


@pytest.mark.parametrize(("env_id", "obs_dim", "act_dim"), PAPER_ENVS)
def test_paper_envs_build_with_their_dimensions(env_id, obs_dim, act_dim):
    env = make_env(env_id, max_episode_steps=37)
    try:
        spec = env_spec(env, env_id, 37)
        assert (spec.obs_dim, spec.act_dim, spec.n_objectives) == (obs_dim, act_dim, 2)
        assert len(spec.action_low) == len(spec.action_high) == act_dim
        assert all(lo < hi for lo, hi in zip(spec.action_low, spec.action_high))
        assert spec.max_episode_steps == 37 and spec.env_id == env_id
        obs, _ = env.reset(seed=0)
        assert obs.shape == (obs_dim,)
        _, reward, *_ = env.step(env.action_space.sample())
        assert np.asarray(reward).shape == (2,)
        assert len(objective_names(env_id, 2)) == 2
    finally:
        env.close()


def test_episode_cap_truncates_at_exactly_the_cap():
    # Swimmer never terminates, so the only way an episode ends is the cap.
    cap = 7
    env = make_env("mo-swimmer-v5", max_episode_steps=cap)
    try:
        env.reset(seed=0)
        flags = [env.step(np.zeros(2, np.float32))[2:4] for _ in range(cap)]
        assert [tr for _, tr in flags] == [False] * (cap - 1) + [True]
        assert not any(te for te, _ in flags)
    finally:
        env.close()


def test_cap_replaces_the_registered_limit():
    # The registered limit is 1000; a cap above it must not be cut short by it.
    env = make_env("mo-swimmer-v5", max_episode_steps=1200)
    try:
        assert env.spec.max_episode_steps == 1200
    finally:
        env.close()


def test_unknown_id_is_an_env_error():
    with pytest.raises(EnvError, match=r"env.id = 'mo-nonexistent-v9': cannot build it"):
        make_env("mo-nonexistent-v9", 10)


def test_discrete_action_env_is_rejected():
    with pytest.raises(EnvError) as info:
        make_env("deep-sea-treasure-v0", 10)
    msg = str(info.value)
    assert "'deep-sea-treasure-v0'" in msg
    assert "Discrete" in msg and "continuous Box" in msg


def test_scalar_reward_env_is_rejected():
    # A plain gymnasium id builds through mo_gymnasium.make but has no reward_space.
    with pytest.raises(EnvError) as info:
        make_env("Pendulum-v1", 10)
    msg = str(info.value)
    assert "'Pendulum-v1'" in msg
    assert "multi-objective" in msg


def test_objective_names_override_fallback_and_mismatch():
    assert objective_names("mo-hopper-2obj-v5", 2) == ["x velocity", "jump height"]
    assert objective_names("mo-hopper-2obj-v5", 2, ["a", "b"]) == ["a", "b"]
    # Unknown env, or a known env with another objective count: generic names.
    assert objective_names("mo-foo-v0", 3) == ["objective 0", "objective 1", "objective 2"]
    assert objective_names("mo-hopper-2obj-v5", 3)[2] == "objective 2"
    with pytest.raises(EnvError, match="3 names"):
        objective_names("mo-hopper-2obj-v5", 2, ["a", "b", "c"])


def test_no_gl_backend_is_chosen_at_import(tmp_path):
    """Importing the stages and stepping an env must not select an OpenGL backend: on a
    headless GPU box without libEGL, MUJOCO_GL=egl made every stage die at import."""
    import os
    import subprocess
    import sys

    code = (
        "import os, numpy as np, stages.cli, pipeline.core.envs as e\n"
        "env = e.make_env('mo-halfcheetah-v5', 5); env.reset(seed=0); env.step(np.zeros(6, np.float32))\n"
        "print(repr(os.environ.get('MUJOCO_GL')))\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, cwd=tmp_path, capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "None"


def test_mujocos_settotalmass_deprecation_is_dropped_and_other_warnings_are_not(capfd):
    """MuJoCo 4's 'settotalmass is deprecated' warning (from Gymnasium's model files, printed from C
    each time a model compiles) does not reach the user; a MuJoCo warning of any other kind does."""
    import mujoco

    capfd.readouterr()
    make_env("mo-halfcheetah-v5", 10).close()
    make_env("mo-hopper-2obj-v5", 10).close()
    model = mujoco.MjModel.from_xml_string(
        '<mujoco><compiler settotalmass="3"/><worldbody><body><geom size=".1"/><joint type="free"/></body>'
        "</worldbody></mujoco>"
    )
    data = mujoco.MjData(model)
    data.qpos[:] = float("nan")
    mujoco.mj_step(model, data)  # an unstable simulation: MuJoCo warns
    err = capfd.readouterr().err
    assert "settotalmass" not in err
    assert "WARNING: Nan, Inf or huge value in QPOS" in err


# Per-env facts: one data file (presets/envs.yaml, pipeline/params/env_facts.py) that every reader reads


def test_per_env_facts_live_in_one_file_and_nowhere_in_the_code():
    """No module of pipeline/ or stages/ holds an env id as a value of its own (a table keyed by
    env ids, say): the per-env facts are in presets/envs.yaml alone. The one env id allowed is the
    default of env.id."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    env_id = re.compile(r"mo-[a-z0-9-]+-v\d+")
    found = []
    for path in sorted([*(root / "pipeline").rglob("*.py"), *(root / "stages").rglob("*.py")]):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and env_id.fullmatch(node.value):
                found.append(f"{path.relative_to(root)}: {node.value}")
    assert found == ["pipeline/params/common.py: mo-halfcheetah-v5"], found  # EnvParams.id's default


def test_per_env_facts_cover_their_envs_consistently():
    from pipeline.params.env_facts import (
        mopderl_values,
        paper_extract,
        paper_extract_envs,
        read_facts,
        reference_points,
    )

    refs, names = reference_points(), read_facts("objective_names")
    assert set(refs) == set(names) and all(len(refs[e]) == len(names[e]) for e in refs)
    # the paper's five envs have its MAPEX values and MOPDERL budgets (appendix tables)
    paper = {"mo-halfcheetah-v5", "mo-hopper-2obj-v5", "mo-walker2d-v5", "mo-swimmer-v5", "mo-ant-2obj-v5"}
    assert set(paper_extract_envs()) == paper and set(read_facts("mopderl")) == paper
    assert paper_extract("mo-hopper-2obj-v5") == (10, 0.1, 20.0) and paper_extract("mo-hopper-v5") is None
    assert mopderl_values("mo-swimmer-v5") == {"total_frames": 1_000_000, "eval_episodes": 1}
    assert objective_names("mo-ant-v5", 3) == ["x velocity", "y velocity", "energy efficiency"]


def test_params_models_fill_their_nulls_from_the_facts():
    from pipeline.params.extract import ExtractParams
    from pipeline.params.mopderl import MopderlParams

    ex = ExtractParams().resolved("mo-walker2d-v5")
    assert (ex.epochs, ex.beta, ex.omega_max) == (20, 0.5, 20.0)
    assert ExtractParams(epochs=3).resolved("mo-walker2d-v5").epochs == 3  # a value set wins
    with pytest.raises(ValueError, match=r"extract.epochs is null but env 'mo-hopper-v5' has no paper values"):
        ExtractParams().resolved("mo-hopper-v5")
    mo = MopderlParams().resolved("mo-hopper-2obj-v5")
    assert (mo.total_frames, mo.eval_episodes) == (1_750_000, 3)
    mo = MopderlParams(eval_episodes=2).resolved("mo-hopper-v5")  # no entry: the defaults, a value set wins
    assert (mo.total_frames, mo.eval_episodes) == (2_000_000, 2)


def test_a_bad_facts_file_is_one_line_naming_it(tmp_path):
    from pipeline.params import ParamsError
    from pipeline.params.env_facts import read_facts

    table = tmp_path / "envs.yaml"
    with pytest.raises(ParamsError, match=f"^{re.escape(str(table))}: file not found"):
        read_facts("reference_point", table)
    table.write_text("reference_point:\n  mo-x-v0: [1.0, oops]\n")
    with pytest.raises(ParamsError, match=r"reference_point.mo-x-v0 = \[1.0, 'oops'\]: expected a list of numbers"):
        read_facts("reference_point", table)
    table.write_text("paper_extract:\n  mo-x-v0: {epochs: 3, beta: 1.0}\n")
    with pytest.raises(
        ParamsError, match=r"paper_extract.mo-x-v0 = .*expected a mapping of \['epochs', 'beta', 'omega_max'\]"
    ):
        read_facts("paper_extract", table)
    with pytest.raises(ParamsError, match=r"expected a mapping `mopderl` of env ids"):
        read_facts("mopderl", table)
