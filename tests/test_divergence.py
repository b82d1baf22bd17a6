"""Training fails loudly (pipeline.core.finite): a NaN in a buffer, a loss or a weight stops the
stage with one line naming the stage, seed, objective, step and what went bad, exit code 3
(bad input: 2), no artifact written and the last good checkpoint left on disk."""

from __future__ import annotations

import copy
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import typer
import yaml
from tqdm import tqdm

from pipeline.core.artifacts import ArtifactError
from pipeline.core.buffer import load_buffer, save_buffer
from pipeline.core.envs import env_spec, make_env
from pipeline.core.finite import CHECK_EVERY, TrainingDiverged, check_finite, first_nonfinite
from pipeline.critics.posthoc import fit_posthoc_critics
from pipeline.params.fit_critics import FitCriticsParams
from pipeline.params.td3 import TD3Params
from pipeline.params.train_pderl import TrainPderlParams
from pipeline.specialists.pderl import PderlRun
from pipeline.specialists.td3_training import SpecialistsRun
from stages.common import DIVERGED_EXIT, run_parts


def error_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("error:")]


# ---------------------------------------------------------------- the check itself


def test_first_nonfinite_names_the_first_bad_tensor_and_prefers_nan():
    ok, nan, inf = torch.ones(3), torch.tensor([1.0, float("nan"), float("inf")]), torch.tensor([float("-inf")])
    assert first_nonfinite([("a", ok), ("ints", torch.arange(3))]) is None
    assert first_nonfinite([]) is None
    assert first_nonfinite([("a", ok), ("b", inf), ("c", nan)]) == ("b", "infinite")
    assert first_nonfinite([("c", nan), ("b", inf)]) == ("c", "NaN")
    with pytest.raises(TrainingDiverged) as info:
        check_finite([("critic loss", nan)], 1200, seed=0, objective=1)
    exc = info.value.within("train_specialist", "/tmp/absent.pt")
    assert (
        str(exc)
        == "train_specialist seed 0 obj 1: critic loss is NaN at step 1200 (no checkpoint had been written yet)"
    )
    exc = TrainingDiverged("an actor weight", "infinite", 7, "update").about(3, [0, 1], "generation 2")
    assert str(exc.within("train_pderl", "/tmp/x.pt", kept=True)) == (
        "train_pderl seed 3 obj 0, 1: an actor weight is infinite at update 7, generation 2 "
        "(the last good checkpoint is kept: /tmp/x.pt)"
    )


# ---------------------------------------------------------------- buffers on load

ATTRS = {"env_id": "test", "objective": 0, "seed": 0, "obs_dim": 3, "act_dim": 2, "n_objectives": 2}


def buffer_rows(n: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {
        "obs": rng.normal(size=(n, 3)).astype(np.float32),
        "action": rng.uniform(-1, 1, size=(n, 2)).astype(np.float32),
        "reward": rng.normal(size=(n, 2)).astype(np.float32),
        "next_obs": rng.normal(size=(n, 3)).astype(np.float32),
        "terminated": np.zeros(n, bool),
        "truncated": np.zeros(n, bool),
        "episode": np.zeros(n, np.int64),
        "episode_step": np.arange(n, dtype=np.int32),
    }


@pytest.mark.parametrize(
    ("name", "value", "shown"),
    [("reward", np.nan, "NaN"), ("obs", np.inf, "+inf"), ("action", -np.inf, "-inf"), ("next_obs", np.nan, "NaN")],
)
def test_load_buffer_refuses_a_non_finite_row(tmp_path, name, value, shown):
    data = buffer_rows(10)
    data[name][6, 1] = value
    data[name][8, 0] = value  # a later bad row: the first one is named
    path = tmp_path / "buffer.zarr"
    save_buffer(path, data, ATTRS)
    with pytest.raises(ArtifactError) as info:
        load_buffer(path)
    assert str(info.value) == f"{path}: array {name!r} holds {shown} in row 6 (its values must be finite)"


# ---------------------------------------------------------------- train_specialist

HOPPER = {"id": "mo-hopper-2obj-v5", "max_episode_steps": 40}
# 300 steps, updates from step 100 (checks at updates 100 and 200: steps 200 and 300),
# checkpoints every 70 steps: 70, 140, 210, 280
AGENT = {"learning_starts": 100, "batch_size": 32, "hidden_sizes": [16, 16], "buffer_size": 180}
TRAIN = {"total_steps": 300, "checkpoint_every": 70, "processes": 1}


def poison_critic_after(monkeypatch, step: int, specialist: int) -> None:
    """After env step `step`, put a NaN into one weight of stacked specialist `specialist`'s critic."""
    real = SpecialistsRun.step

    def step_then_poison(self):
        records = real(self)
        if self.t == step:
            e = self.state.critic.n_members // self.state.n
            with torch.no_grad():
                self.state.critic.weights[0][specialist * e, 0, 0] = float("nan")
        return records

    monkeypatch.setattr(SpecialistsRun, "step", step_then_poison)


@pytest.mark.parametrize(
    ("poison_at", "found_at"),
    [
        (150, 200),  # found by the check every CHECK_EVERY updates (update 100 = step 200)
        (205, 210),  # found by the check before the checkpoint at step 210, which is not saved
    ],
)
def test_train_specialist_stops_at_a_nan_critic(tmp_path, write_params, cli, monkeypatch, poison_at, found_at):
    assert CHECK_EVERY == 100  # the steps above assume it
    params = write_params(tmp_path, {"env": HOPPER, "td3": AGENT, "train_specialist": TRAIN})
    poison_critic_after(monkeypatch, poison_at, specialist=1)
    out = tmp_path / "out"
    result = cli("train-specialist", "--seed", 0, "--out", out, "--params", params)
    ckpt = tmp_path / ".out.resume" / "specialist_state_obj0-obj1.pt"
    assert result.exit_code == DIVERGED_EXIT == 3, result.stderr
    assert error_lines(result.stderr) == [
        f"error: train_specialist seed 0 obj 1: critic loss is NaN at step {found_at} "
        f"(the last good checkpoint is kept: {ckpt})"
    ]
    assert "Traceback" not in result.stderr
    assert not out.exists() or not any(out.rglob("*"))  # no artifact
    state = torch.load(ckpt, weights_only=True)["state"]
    assert state["counters"]["t"] == 140  # the last checkpoint before the NaN, not a diverged one
    assert all(torch.isfinite(v).all() for v in state["nets"]["critic"].values())


def test_a_sigterm_checkpoint_of_a_diverged_state_is_not_written(tmp_path, write_params, cli, monkeypatch):
    """SIGTERM at step 155, between the periodic checkpoints (140, 210) and before the check every
    CHECK_EVERY updates (step 200), after a NaN went into a critic weight at step 150: the
    SIGTERM checkpoint runs the full check, so the divergence line comes instead of a checkpoint
    of the diverged state, and the last good one (step 140) stays."""
    import os
    import signal

    params = write_params(tmp_path, {"env": HOPPER, "td3": AGENT, "train_specialist": TRAIN})
    poison_critic_after(monkeypatch, 150, specialist=0)
    poisoned = SpecialistsRun.step

    def step_then_sigterm(self):
        records = poisoned(self)
        if self.t == 155:
            os.kill(os.getpid(), signal.SIGTERM)
        return records

    monkeypatch.setattr(SpecialistsRun, "step", step_then_sigterm)
    out = tmp_path / "out"
    result = cli("train-specialist", "--seed", 0, "--out", out, "--params", params)
    ckpt = tmp_path / ".out.resume" / "specialist_state_obj0-obj1.pt"
    assert result.exit_code == DIVERGED_EXIT, result.stderr
    lines = error_lines(result.stderr)
    assert len(lines) == 1 and re.fullmatch(
        rf"error: train_specialist seed 0 obj 0: .* is NaN at step 155 \(the last good checkpoint is kept: {re.escape(str(ckpt))}\)",
        lines[0],
    ), lines
    assert "checkpoint written" not in result.stderr
    state = torch.load(ckpt, weights_only=True)["state"]
    assert state["counters"]["t"] == 140
    assert all(torch.isfinite(v).all() for v in state["nets"]["critic"].values())


# Worker processes (train_specialist.processes > 1): the part raises in a spawned process, which
# imports this function from this module.


def diverging_part(which: int, threads: int, *, send) -> None:
    if which == 1:
        exc = TrainingDiverged("critic loss", "NaN", 1200, seed=0, objective=1)
        raise exc.within("train_specialist", "/tmp/specialist_state_obj1.pt", kept=True)


def test_a_worker_that_diverges_is_reported_as_the_stage_would(capsys):
    with tqdm(disable=True) as bar, pytest.raises(typer.Exit) as info:
        run_parts(diverging_part, [(0,), (1,)], bar, lambda i: f"part {i}")
    assert info.value.exit_code == 3
    err = capsys.readouterr().err
    assert error_lines(err) == [
        "error: train_specialist seed 0 obj 1: critic loss is NaN at step 1200 "
        "(the last good checkpoint is kept: /tmp/specialist_state_obj1.pt)"
    ]
    assert "Traceback" not in err


# ---------------------------------------------------------------- extract and fit_critics on tiny specialists

TINY = {
    "env": {"id": "mo-halfcheetah-v5", "max_episode_steps": 40, "reference_point": [-100.0, -4500.0]},
    "seeds": [0],
    "objectives": [0, 1],
    "td3": {"learning_starts": 200, "batch_size": 32, "hidden_sizes": [16, 16]},
    "train_specialist": {"total_steps": 300},
    "fit_critics": {"steps": 30, "check_every": 0, "batch_size": 32, "hidden_sizes": [16, 16]},
    "extract": {
        "iterations": 2,
        "child_buffer_size": 200,
        "eval_episodes": 1,
        "warmup_steps": 10,
        "warmup_batch_size": 32,
        "epochs": 1,
        "beta": 1.0,
        "omega_max": 1.0,
        "batch_size": 32,
        "hidden_sizes": [16, 16],
    },
}


def tiny_params_file(path: Path, **extract) -> Path:
    p = copy.deepcopy(TINY)
    p["extract"].update(extract)
    path.write_text(yaml.safe_dump(p))
    return path


@pytest.fixture(scope="module")
def specialists(tmp_path_factory) -> Path:
    from typer.testing import CliRunner

    from stages.cli import app

    root = tmp_path_factory.mktemp("specs")
    params = tiny_params_file(root / "params.yaml")
    r = CliRunner().invoke(app, ["train-specialist", "--seed", "0", "--out", str(root), "--params", str(params)])
    assert r.exit_code == 0, r.stderr
    return root


def test_fit_critics_refuses_a_buffer_with_a_nan_reward(specialists, tmp_path, cli):
    spec = tmp_path / "obj0"
    shutil.copytree(specialists / "obj0", spec)
    data, attrs = load_buffer(spec / "buffer.zarr")
    data["reward"][17, 1] = np.nan
    save_buffer(spec / "buffer.zarr", data, attrs)
    params = tiny_params_file(tmp_path / "params.yaml")
    out = tmp_path / "out"
    result = cli("fit-critics", "--objective", 0, "--seed", 0, "--specialist", spec, "--out", out, "--params", params)
    assert result.exit_code == 2, result.stderr
    assert error_lines(result.stderr) == [
        f"error: {spec / 'buffer.zarr'}: array 'reward' holds NaN in row 17 (its values must be finite)"
    ]
    assert not out.exists()


@pytest.mark.parametrize(
    ("k", "poison", "loss"),
    [
        (1, "critics", "the advantage-weighted loss"),  # K = 1 on a CPU: the reference make_child
        (2, "critics", "the advantage-weighted loss"),  # K = 2: the stacked children
        (1, "actors", "the warm-up loss"),  # NaN parents: their mean action is the warm-up target
    ],
)
def test_extract_stops_at_a_nan_child_loss(specialists, tmp_path, cli, monkeypatch, k, poison, loss):
    """A NaN in the critics (or the parents) from iteration 2 on makes the child's loss NaN:
    the stage stops with one line, writes no population.pt and keeps the checkpoint of
    iteration 1."""
    import pipeline.extraction.run as run_mod

    real = run_mod.make_children
    calls = []

    def poisoned(returns, actors, buffers, critics, *args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            with torch.no_grad():
                for net in critics if poison == "critics" else actors:
                    next(net.parameters()).view(-1)[0] = float("nan")
        return real(returns, actors, buffers, critics, *args, **kwargs)

    monkeypatch.setattr(run_mod, "make_children", poisoned)
    params = tiny_params_file(tmp_path / "params.yaml", children_per_iteration=k)
    out, resume = tmp_path / "out", tmp_path / "resume"
    result = cli(
        "extract", "--seed", 0, "--specialists", specialists, "--out", out, "--resume-dir", resume, "--params", params
    )
    ckpt = resume / "extract" / "mapex_td3" / "seed0" / "state.pt"
    assert result.exit_code == 3, result.stderr
    lines = error_lines(result.stderr)
    child = r", child [12] of 2" if k == 2 else ""
    pattern = (
        rf"error: extract mapex_td3 seed 0: {loss} is NaN at step \d+, iteration 2{child} "
        rf"\(the last good checkpoint is kept: {re.escape(str(ckpt))}\)"
    )
    assert len(lines) == 1 and re.fullmatch(pattern, lines[0]), lines
    assert "Traceback" not in result.stderr
    assert not (out / "population.pt").exists() and not (out / "history.csv").exists()
    assert torch.load(ckpt, weights_only=True)["n_items"] == 2 + k  # the specialists and iteration 1


# ---------------------------------------------------------------- the other loops, in the library


def test_posthoc_fit_diverges_on_a_nan_target_policy():
    from pipeline.core.nets import Actor

    data = buffer_rows(64)
    policy = Actor(3, 2, [8], [-1.0, -1.0], [1.0, 1.0])
    with torch.no_grad():
        policy.net[0].weight[0, 0] = float("nan")  # NaN next actions: NaN targets, NaN loss
    cfg = FitCriticsParams(steps=30, check_every=0, batch_size=16, hidden_sizes=[8], device="cpu")
    with pytest.raises(TrainingDiverged) as info:
        fit_posthoc_critics(data, policy, [0, 1], cfg, np.random.default_rng(0), torch.Generator().manual_seed(0))
    assert str(info.value) == "critic loss is NaN at step 30"


@pytest.fixture(scope="module")
def hopper_spec():
    env = make_env("mo-hopper-2obj-v5", 30)
    spec = env_spec(env, "mo-hopper-2obj-v5", 30)
    env.close()
    return spec


def pderl_run(spec) -> PderlRun:
    td3 = TD3Params(learning_starts=16, batch_size=16, hidden_sizes=[16], buffer_size=500)
    cfg = TrainPderlParams(
        total_frames=200, population_size=3, mini_buffer_size=200, crossover_transitions=64,
        crossover_batch_size=32, mutation_states=32, device="cpu",
    )  # fmt: skip
    return PderlRun(spec, td3, cfg, objective=1, seed=4)


def test_pderl_agent_updates_diverge_every_check_every(hopper_spec):
    run = pderl_run(hopper_spec)
    rng = np.random.default_rng(0)
    o, a = hopper_spec.obs_dim, hopper_spec.act_dim
    for i in range(40):
        run.agent.add(rng.normal(size=o).astype(np.float32), rng.uniform(-1, 1, a).astype(np.float32),
                      rng.normal(size=2), rng.normal(size=o).astype(np.float32), False, False, 0, i)  # fmt: skip
    run.agent.train(CHECK_EVERY - 1)
    with torch.no_grad():
        run.agent.state.critic.weights[1][0, 0, 0] = float("nan")
    with pytest.raises(TrainingDiverged) as info:
        run.agent.train(5)
    assert (info.value.what, info.value.problem, info.value.step, info.value.unit) == (
        "critic loss",
        "NaN",
        CHECK_EVERY,
        "update",
    )


def test_pderl_generation_check_names_seed_objective_and_actor(hopper_spec):
    run = pderl_run(hopper_spec)
    run.check_finite()  # a fresh run is finite
    with torch.no_grad():
        run.population[2].actor.net[0].weight[1, 1] = float("nan")  # as a bad mutation would leave it
    with pytest.raises(TrainingDiverged) as info:
        run.check_finite()
    assert str(info.value) == "seed 4 obj 1: a weight of population actor 2 is NaN at generation 0"
    run = pderl_run(hopper_spec)
    with torch.no_grad():
        run.agent.state.critic_target.biases[0][0, 0, 0] = float("nan")
    with pytest.raises(
        TrainingDiverged, match=r"^seed 4 obj 1: a target critic weight is NaN at update 0, generation 0$"
    ):
        run.check_finite()


def test_morld_check_names_the_agent_and_network(hopper_spec):
    pytest.importorskip("morl_baselines")
    from pipeline.baselines.morld import MorldRun
    from pipeline.params.morld import MorldParams

    cfg = MorldParams(
        total_frames=100, exchange_every=50, pop_size=2, hidden_sizes=[8], batch_size=16, learning_starts=20,
        buffer_size=200, update_passes=1, front_eval_episodes=1, eval_episodes=1, device="cpu",
    )  # fmt: skip
    run = MorldRun(hopper_spec, cfg, seed=2)
    run.check_finite()
    with torch.no_grad():
        next(run.algo.population[1].wrapped.qf2.parameters()).view(-1)[3] = float("nan")
    with pytest.raises(TrainingDiverged, match=r"^seed 2: a weight of agent 1's critic 2 is NaN at exchange 0$"):
        run.check_finite()
