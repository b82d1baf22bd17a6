"""Stage train_specialist: the real `mapex train-specialist` command on the tiny preset.

Every artifact is reloaded through the real loaders and checked against the run's params;
bad params fail fast with one readable message and write nothing; same seed = same bits; a
run killed mid-way resumes from its checkpoint to the same bits (and a changed one starts over).
"""

from __future__ import annotations

import csv
import io
import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.core.artifacts import torch_load_checked
from pipeline.core.buffer import FIELDS, FORMAT, FORMAT_VERSION, load_buffer
from pipeline.core.checkpoint import CRITICS_FORMAT, POLICY_FORMAT, load_critics, load_policy
from pipeline.core.drive import run_to_end
from pipeline.core.envs import env_spec, make_env
from pipeline.core.envstate import env_state, restore_env_state
from pipeline.core.resume import FORMAT as CHECKPOINT_FORMAT
from pipeline.core.resume import FORMAT_VERSION as CHECKPOINT_VERSION
from pipeline.core.resume import Checkpoint
from pipeline.params.td3 import TD3Params
from pipeline.params.train_specialist import TrainSpecialistParams
from pipeline.specialists.td3_training import SpecialistsRun, train_specialist

# The stage command end to end, often in subprocesses: `make test-fast` leaves this file out.
pytestmark = pytest.mark.integration

CAP = 100  # the tiny preset's episode cap
TOTAL = 350  # its total_steps

# Hopper with a cap of 18 steps: at seed 0 some episodes fall (terminated) and some are cut by
# the cap (truncated); one even falls on its 18th step, so both flags are set there.
HOPPER = {"env": {"id": "mo-hopper-2obj-v5", "max_episode_steps": 18}, "td3": {"secondary_critics": False}}


@dataclass
class Run:
    out: Path
    objective: int
    seed: int
    stderr: str


def train(tmp_path_factory, write_params, mapex, name: str, objective: int, seed: int, overrides=None) -> Run:
    d = tmp_path_factory.mktemp(name)
    params = write_params(d, overrides)
    proc = mapex(
        "train-specialist", "--objective", objective, "--seed", seed, "--out", d / "out", "--params", params, cwd=d
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert sorted(p.name for p in (d / "out").iterdir()) == [f"obj{objective}"]
    return Run(d / "out" / f"obj{objective}", objective, seed, proc.stderr)


@pytest.fixture(scope="module")
def cheetah(tmp_path_factory, write_params, mapex) -> Run:
    """HalfCheetah, objective 1 (energy), secondary critics on: 2 objectives x 2 heads."""
    return train(tmp_path_factory, write_params, mapex, "cheetah", objective=1, seed=0)


@pytest.fixture(scope="module")
def hopper(tmp_path_factory, write_params, mapex) -> Run:
    """Hopper, objective 0, secondary critics off: the primary's twin heads only."""
    return train(tmp_path_factory, write_params, mapex, "hopper", objective=0, seed=0, overrides=HOPPER)


# --- artifacts of a successful run --------------------------------------------------------


def check_episodes(data: dict[str, np.ndarray], cap: int) -> list[np.ndarray]:
    """Check the episode bookkeeping of a buffer; return the row indices of each ended episode."""
    ep, step = data["episode"], data["episode_step"]
    term, trunc = data["terminated"], data["truncated"]
    assert ep[0] == 0 and step[0] == 0
    ends = term | trunc
    # A new episode starts exactly after a row that ended one.
    new_episode = np.diff(ep) != 0
    assert np.array_equal(new_episode, ends[:-1])
    assert np.all(np.diff(ep) <= 1)
    # Step counters restart at 0 after an end and count up by one otherwise.
    assert np.all(step[1:][ends[:-1]] == 0)
    assert np.all(np.diff(step)[~ends[:-1]] == 1)
    assert step.max() < cap
    # Truncated exactly where the cap cut an episode: its cap-th step.
    assert np.array_equal(trunc, step == cap - 1)
    # Both flags only when an episode terminated on the cap step itself.
    assert np.all(step[term & trunc] == cap - 1)
    # Within an episode the next row starts where this one ended.
    assert np.array_equal(data["next_obs"][:-1][~ends[:-1]], data["obs"][1:][~ends[:-1]])
    return [np.flatnonzero(ep == e) for e in np.unique(ep[ends])]


def read_returns(out: Path) -> list[dict[str, str]]:
    with open(out / "returns.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_outputs_are_exactly_the_four_artifacts(cheetah):
    assert sorted(p.name for p in cheetah.out.iterdir()) == ["buffer.zarr", "critics.pt", "policy.pt", "returns.csv"]


def test_buffer_holds_every_step_with_its_metadata(cheetah):
    data, attrs = load_buffer(cheetah.out / "buffer.zarr")
    assert attrs["format"] == FORMAT and attrs["format_version"] == FORMAT_VERSION
    assert attrs["env_id"] == "mo-halfcheetah-v5" and attrs["objective"] == 1 and attrs["seed"] == 0
    assert (attrs["obs_dim"], attrs["act_dim"], attrs["n_objectives"]) == (17, 6, 2)
    assert attrs["max_episode_steps"] == CAP and attrs["n_transitions"] == TOTAL
    assert {name: data[name].shape for name in FIELDS} == {
        "obs": (TOTAL, 17),
        "action": (TOTAL, 6),
        "reward": (TOTAL, 2),
        "next_obs": (TOTAL, 17),
        "terminated": (TOTAL,),
        "truncated": (TOTAL,),
        "episode": (TOTAL,),
        "episode_step": (TOTAL,),
    }
    assert np.all(np.abs(data["action"]) <= 1.0)
    # The energy objective is -||a||^2 based: never positive, and not constant.
    assert np.all(data["reward"][:, 1] <= 0) and data["reward"][:, 1].std() > 0


def test_cheetah_episodes_are_all_cut_by_the_cap(cheetah):
    data, _ = load_buffer(cheetah.out / "buffer.zarr")
    episodes = check_episodes(data, CAP)
    assert not data["terminated"].any()  # HalfCheetah has no terminal states
    assert np.flatnonzero(data["truncated"]).tolist() == [99, 199, 299]
    assert len(episodes) == 3
    assert data["episode"][-1] == 3 and data["episode_step"][-1] == TOTAL - 1 - 300  # the 4th is still running


def test_hopper_episodes_terminate_and_truncate(hopper):
    data, attrs = load_buffer(hopper.out / "buffer.zarr")
    assert attrs["env_id"] == "mo-hopper-2obj-v5" and attrs["n_transitions"] == TOTAL
    check_episodes(data, 18)
    only_term = data["terminated"] & ~data["truncated"]
    only_trunc = data["truncated"] & ~data["terminated"]
    assert only_term.any() and only_trunc.any()  # both kinds of end occur in this run


@pytest.mark.parametrize("run_name", ["cheetah", "hopper"])
def test_returns_csv_matches_the_buffer_episodes(run_name, request):
    run: Run = request.getfixturevalue(run_name)
    data, attrs = load_buffer(run.out / "buffer.zarr")
    episodes = check_episodes(data, attrs["max_episode_steps"])
    rows = read_returns(run.out)
    assert len(rows) == len(episodes) > 0
    names = list(rows[0])[4:]
    assert list(rows[0])[:4] == ["episode", "step", "length", "terminated"] and names == ["obj0", "obj1"]
    for row, idx in zip(rows, episodes):
        assert int(row["episode"]) == data["episode"][idx[0]]
        assert int(row["length"]) == len(idx)
        assert int(row["step"]) == idx[-1] + 1
        assert int(row["terminated"]) == int(data["terminated"][idx[-1]])
        returns = data["reward"][idx].astype(np.float64).sum(axis=0)
        np.testing.assert_allclose([float(row[n]) for n in names], returns, rtol=1e-5, atol=1e-4)


def test_policy_loads_and_acts_in_bounds(cheetah):
    actor, meta = load_policy(cheetah.out / "policy.pt")
    assert meta["env_id"] == "mo-halfcheetah-v5" and meta["objective"] == 1 and meta["seed"] == 0
    assert (meta["obs_dim"], meta["act_dim"], meta["n_objectives"]) == (17, 6, 2)
    assert meta["hidden_sizes"] == [32, 32]
    assert set(meta["params"]) == {"env", "td3", "train_specialist"}
    assert TrainSpecialistParams(**meta["params"]["train_specialist"]).total_steps == TOTAL
    assert TD3Params(**meta["params"]["td3"]).hidden_sizes == [32, 32]
    # only what inputs and params fix: no provenance, no scoring or labelling env key (a change
    # to those must not change the bytes that extraction and the rest hash)
    assert "provenance" not in meta and set(meta["params"]["env"]) == {"id", "max_episode_steps", "reward_terms"}
    data, _ = load_buffer(cheetah.out / "buffer.zarr")
    with torch.no_grad():
        a = actor(torch.from_numpy(data["obs"][:50]))
    assert a.shape == (50, 6)
    assert torch.all(a >= torch.tensor(meta["action_low"])) and torch.all(a <= torch.tensor(meta["action_high"]))
    raw = torch_load_checked(cheetah.out / "policy.pt", POLICY_FORMAT, 1)
    # 45 actor updates moved the actor away from its slowly-following target.
    assert any(not torch.equal(v, raw["actor_target"][k]) for k, v in raw["actor"].items())


def test_critics_cover_every_objective_when_secondary_is_on(cheetah):
    online, target, meta = load_critics(cheetah.out / "critics.pt")
    assert meta["objectives"] == [0, 1] and meta["buffer_objective"] == 1 and meta["source"] == "joint"
    assert online.n_members == target.n_members == 4
    assert online.weights[0].shape == (4, 17 + 6, 32)
    data, _ = load_buffer(cheetah.out / "buffer.zarr")
    obs, act = torch.from_numpy(data["obs"][:20]), torch.from_numpy(data["action"][:20])
    with torch.no_grad():
        assert online.twin_min(obs, act).shape == (2, 20)
        assert not torch.equal(online(obs, act), target(obs, act))


def test_critics_cover_only_the_primary_when_secondary_is_off(hopper):
    online, target, meta = load_critics(hopper.out / "critics.pt")
    assert meta["objectives"] == [0] and meta["buffer_objective"] == 0
    assert online.n_members == target.n_members == 2
    assert online.weights[0].shape == (2, 11 + 3, 32)
    assert (
        torch_load_checked(hopper.out / "critics.pt", CRITICS_FORMAT, 1)["meta"]["params"]["td3"]["secondary_critics"]
        is False
    )


# --- determinism --------------------------------------------------------------------------


def state_dicts(out: Path) -> dict[str, torch.Tensor]:
    pol = torch_load_checked(out / "policy.pt", POLICY_FORMAT, 1)
    cri = torch_load_checked(out / "critics.pt", CRITICS_FORMAT, 1)
    flat = {}
    for part, sd in (
        ("actor", pol["actor"]),
        ("actor_target", pol["actor_target"]),
        ("online", cri["online"]),
        ("target", cri["target"]),
    ):
        flat |= {f"{part}.{k}": v for k, v in sd.items()}
    return flat


def test_same_seed_twice_gives_identical_bits(cheetah, tmp_path_factory, write_params, mapex):
    again = train(tmp_path_factory, write_params, mapex, "cheetah_again", objective=1, seed=0)
    a, _ = load_buffer(cheetah.out / "buffer.zarr")
    b, _ = load_buffer(again.out / "buffer.zarr")
    for name in FIELDS:
        assert a[name].tobytes() == b[name].tobytes(), name
    sa, sb = state_dicts(cheetah.out), state_dicts(again.out)
    assert sa.keys() == sb.keys()
    for k in sa:
        assert torch.equal(sa[k], sb[k]), k
    assert (cheetah.out / "returns.csv").read_text() == (again.out / "returns.csv").read_text()


def test_another_seed_gives_other_data_and_weights(cheetah, tmp_path_factory, write_params, mapex):
    other = train(tmp_path_factory, write_params, mapex, "cheetah_seed1", objective=1, seed=1)
    a, _ = load_buffer(cheetah.out / "buffer.zarr")
    b, attrs = load_buffer(other.out / "buffer.zarr")
    assert attrs["seed"] == 1
    assert not np.array_equal(a["obs"], b["obs"]) and not np.array_equal(a["action"], b["action"])
    sa, sb = state_dicts(cheetah.out), state_dicts(other.out)
    assert not torch.equal(sa["actor.net.0.weight"], sb["actor.net.0.weight"])
    assert not torch.equal(sa["online.weights.0"], sb["online.weights.0"])


def test_a_slot_of_the_imported_kind_is_the_td3_specialist_with_its_source(cheetah, tmp_path, write_params, mapex):
    """--kind imported (stage train_specialist_imported: an objective without an import entry) trains
    the same specialist as --kind td3, bit for bit; only policy.pt's metadata adds its source."""
    params = write_params(tmp_path)
    proc = mapex(
        "train-specialist", "--objective", 1, "--kind", "imported", "--out", tmp_path / "out", "--params", params,
        cwd=tmp_path,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    slot = tmp_path / "out" / "obj1"
    a, _ = load_buffer(cheetah.out / "buffer.zarr")
    b, _ = load_buffer(slot / "buffer.zarr")
    assert all(a[name].tobytes() == b[name].tobytes() for name in FIELDS)
    sa, sb = state_dicts(cheetah.out), state_dicts(slot)
    assert sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)
    assert (cheetah.out / "critics.pt").read_bytes() == (slot / "critics.pt").read_bytes()
    _, td3_meta = load_policy(cheetah.out / "policy.pt")
    _, meta = load_policy(slot / "policy.pt")
    assert "source" not in td3_meta and meta == td3_meta | {"source": {"trained": "td3"}}


# --- failures -----------------------------------------------------------------------------


def error_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("error:")]


BAD_PARAMS = [
    ({"td3": {"gamma": 1.5}}, ["td3.gamma = 1.5", "less than 1"]),
    ({"td3": {"batch_sizee": 64}}, ["td3.batch_sizee", "unknown key"]),
    ({"td3": {"learning_starts": 32}}, ["learning_starts (32) must be >= batch_size (64)"]),
    ({"td3": {"learning_starts": 350}}, ["td3.learning_starts (350) must be < train_specialist.total_steps (350)"]),
    ({"train_specialist": {"gamma": 0.98}}, ["key(s) moved to section `td3`", "train_specialist.gamma -> td3.gamma"]),
    ({"env": {"max_episode_steps": 0}}, ["env.max_episode_steps = 0", "greater than 0"]),
    ({"bogus_section": {"x": 1}}, ["unknown top-level key(s) ['bogus_section']"]),
    ({"env": {"id": "mo-nonexistent-v9"}}, ["env.id = 'mo-nonexistent-v9'", "cannot build it"]),
]


def check_failure(exit_code: int, stderr: str, expected: list[str]) -> None:
    assert exit_code == 2, stderr
    assert "Traceback" not in stderr
    assert len(error_lines(stderr)) == 1, stderr
    for fragment in expected:
        assert fragment in stderr, (fragment, stderr)


def test_bad_params_exit_2_with_one_message_and_write_nothing(tmp_path, write_params, mapex):
    """The real console command, in its own process."""
    overrides, expected = BAD_PARAMS[0]
    params = write_params(tmp_path, overrides)
    out = tmp_path / "out" / "obj0"
    proc = mapex("train-specialist", "--objective", 0, "--out", out, "--params", params, cwd=tmp_path)
    check_failure(proc.returncode, proc.stderr, expected)
    assert proc.stdout == ""
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("overrides", "expected"),
    BAD_PARAMS,
    ids=[
        "out-of-range",
        "unknown-key",
        "cross-field",
        "cross-section",
        "moved-key",
        "env-section",
        "top-level",
        "env-id",
    ],
)
def test_bad_params_messages(overrides, expected, tmp_path, write_params, cli):
    """The same command in-process (interpreter start-up costs seconds here)."""
    params = write_params(tmp_path, overrides)
    result = cli("train-specialist", "--objective", 0, "--out", tmp_path / "out" / "obj0", "--params", params)
    check_failure(result.exit_code, result.stderr, expected)
    assert not (tmp_path / "out").exists()


def test_objective_out_of_range_is_a_clear_error(tiny_params, tmp_path, cli):
    result = cli("train-specialist", "--objective", 2, "--out", tmp_path / "out", "--params", tiny_params)
    check_failure(result.exit_code, result.stderr, [])
    assert error_lines(result.stderr) == ["error: --objective 2: env mo-halfcheetah-v5 has objectives 0..1"]
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("args", "line"),
    [
        (["--kind", "pderl", "--objective", "0"], "error: --kind 'pderl': expected one of td3, imported"),
        (["--kind", "imported"], "error: --kind imported: name the objectives to train (--objective), those without"),
    ],
)
def test_kind_must_be_known_and_imported_names_its_objectives(args, line, tiny_params, tmp_path, cli):
    result = cli("train-specialist", *args, "--out", tmp_path / "out", "--params", tiny_params)
    check_failure(result.exit_code, result.stderr, [])
    assert error_lines(result.stderr)[0].startswith(line)
    assert not (tmp_path / "out").exists()


def test_missing_params_file_is_a_clear_error(tmp_path, cli):
    result = cli("train-specialist", "--objective", 0, "--out", tmp_path / "out", "--params", tmp_path / "nope.yaml")
    check_failure(result.exit_code, result.stderr, [])
    assert error_lines(result.stderr) == [f"error: {tmp_path / 'nope.yaml'}: params file not found"]
    assert not (tmp_path / "out").exists()


# --- the training loop in-process ---------------------------------------------------------


def test_update_schedule_and_episode_records(monkeypatch):
    """Updates start at learning_starts, one per step; every policy_freq-th one moves the actor."""
    import pipeline.specialists.td3 as td3_mod

    calls: list[bool] = []
    real_update = td3_mod.stacked_update

    def counting_update(state, batch, noise, update_actor, **kw):
        calls.append(update_actor)
        assert batch.obs.shape == (1, 8, 8) and noise.shape == (1, 8, 2)
        return real_update(state, batch, noise, update_actor, **kw)

    monkeypatch.setattr(td3_mod, "stacked_update", counting_update)
    td3 = TD3Params(learning_starts=30, batch_size=8, hidden_sizes=[4], buffer_size=100, policy_freq=3)
    cfg = TrainSpecialistParams(total_steps=40)
    env = make_env("mo-swimmer-v5", 15)
    spec = env_spec(env, "mo-swimmer-v5", 15)
    seen: list[tuple[int, int | None]] = []
    result = train_specialist(
        env, spec, td3, cfg, 0, 0, torch.device("cpu"), on_step=lambda t, r: seen.append((t, r and r.episode))
    )
    env.close()
    assert calls == [False, False, True] * 3 + [False]
    assert [t for t, _ in seen] == list(range(1, 41))
    assert [(t, e) for t, e in seen if e is not None] == [(15, 0), (30, 1)]
    assert [(r.end_step, r.length, r.terminated) for r in result.episodes] == [(15, 15, False), (30, 15, False)]
    assert len(result.buffer["obs"]) == 40


def test_out_of_range_objective_in_the_core():
    env = make_env("mo-swimmer-v5", 15)
    spec = env_spec(env, "mo-swimmer-v5", 15)
    td3 = TD3Params(learning_starts=30, batch_size=8, hidden_sizes=[4])
    cfg = TrainSpecialistParams(total_steps=40)
    with pytest.raises(ValueError, match="objective 5 out of range"):
        train_specialist(env, spec, td3, cfg, 5, 0, torch.device("cpu"))
    env.close()


# --- checkpoints and resume ---------------------------------------------------------------
#
# Hopper (contacts, falls and cap cuts) with a 40-step cap, 300 steps, learning from step 100,
# a 180-row ring (it wraps at step 180) and a checkpoint every 70 steps: at 70 (still acting
# at random), 140 (ring filling) and 210, 280 (ring full, wrapped).

RESUME = {
    "env": {"id": "mo-hopper-2obj-v5", "max_episode_steps": 40},
    "td3": {"learning_starts": 100, "batch_size": 32, "hidden_sizes": [16, 16], "buffer_size": 180},
    "train_specialist": {"total_steps": 300, "checkpoint_every": 70},
}
RESUME_TD3 = TD3Params(**RESUME["td3"])
RESUME_CFG = TrainSpecialistParams(**RESUME["train_specialist"], device="cpu")
PAPER_ENVS = ["mo-hopper-2obj-v5", "mo-halfcheetah-v5", "mo-ant-2obj-v5", "mo-walker2d-v5", "mo-swimmer-v5"]

# The same checks on CUDA, where the update runs as captured graphs (or eagerly) and the
# minibatch rows come from device generators. Results on CUDA are reproducible up to the GPU's
# reduction kernels (docs/manual.md, "On a GPU"), so the restored run is compared with the tolerance
# of the graphs-vs-eager test, not bit for bit. The CPU case runs everywhere and checks these
# tests themselves; the CUDA cases skip without a GPU (benchmarks/device/check.sh runs them).

DEVICES = [
    pytest.param("cpu", False, id="cpu"),
    pytest.param(
        "cuda",
        True,
        id="cuda-graphs",
        marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU"),
    ),
    pytest.param(
        "cuda",
        False,
        id="cuda-eager",
        marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU"),
    ),
]


def assert_close_results(a, b) -> None:
    for x, y in zip(a, b, strict=True):
        assert (x.seed, x.objective) == (y.seed, y.objective)
        assert [(e.episode, e.end_step) for e in x.episodes] == [(e.episode, e.end_step) for e in y.episodes]
        np.testing.assert_allclose(x.buffer["obs"], y.buffer["obs"], rtol=1e-3, atol=1e-3)
        for part in ("actor", "actor_target", "critic", "critic_target"):
            for p, q in zip(getattr(x, part).parameters(), getattr(y, part).parameters(), strict=True):
                torch.testing.assert_close(p.detach().cpu(), q.detach().cpu(), rtol=1e-4, atol=1e-5)


def transitions(env, steps: int) -> list[np.ndarray]:
    """What `steps` steps of random actions give (episodes restart on an end), flattened."""
    out = []
    for _ in range(steps):
        a = env.action_space.sample()
        o, r, term, trunc, info = env.step(a)
        out.append(np.concatenate([a, o, r, [term, trunc, info.get("x_velocity", 0.0)]]))
        if term or trunc:
            out.append(env.reset()[0])
    return out


@pytest.mark.parametrize("env_id", PAPER_ENVS)
def test_env_state_restores_a_mujoco_env_mid_episode_exactly(env_id):
    """A fresh env given a saved env_state steps, ends and resets exactly as the saved one
    goes on (the physics with the solver's warm start, Ant's pre-step body positions, the
    time-limit count, the env's and its action sampler's RNGs)."""
    env = make_env(env_id, 20)
    env.reset(seed=3)
    env.action_space.seed(4)
    transitions(env, 27)  # an episode cut at 20, then 7 steps into the next
    buf = io.BytesIO()
    torch.save(env_state(env), buf)  # through a file, as a checkpoint goes
    expected = transitions(env, 60)  # crosses three more episode ends
    other = make_env(env_id, 20)
    other.reset(seed=99)
    other.action_space.seed(98)
    transitions(other, 5)
    restore_env_state(other, torch.load(io.BytesIO(buf.getvalue()), weights_only=True))
    got = transitions(other, 60)
    assert len(got) == len(expected)
    for x, y in zip(got, expected):
        assert x.tobytes() == y.tobytes()
    env.close()
    other.close()


def test_env_state_refuses_envs_it_cannot_restore():
    """Only MuJoCo physics behind gymnasium's standard wrappers: anything else is refused
    with a reason (the stage then trains without checkpoints and says why)."""
    import gymnasium as gym

    from pipeline.core.envstate import EnvStateError, env_checkpoint_problem

    pendulum = gym.make("Pendulum-v1")
    assert "not a MuJoCo env" in env_checkpoint_problem(pendulum)
    with pytest.raises(EnvStateError, match="not a MuJoCo env"):
        env_state(pendulum)
    recorded = gym.wrappers.RecordEpisodeStatistics(make_env("mo-swimmer-v5", 20))
    assert "RecordEpisodeStatistics" in env_checkpoint_problem(recorded)
    assert env_checkpoint_problem(make_env("mo-swimmer-v5", 20)) is None


def hopper_run(jobs, device: str = "cpu", graphs: bool = False):
    envs = [make_env("mo-hopper-2obj-v5", 40) for _ in jobs]
    td3 = RESUME_TD3.model_copy(update={"cuda_graphs": graphs})
    cfg = RESUME_CFG.model_copy(update={"device": device})
    return SpecialistsRun(envs, env_spec(envs[0], "mo-hopper-2obj-v5", 40), td3, cfg, jobs, torch.device(device))


def assert_same_results(a, b) -> None:
    for x, y in zip(a, b, strict=True):
        assert (x.seed, x.objective, x.objectives) == (y.seed, y.objective, y.objectives)
        for name in FIELDS:
            assert x.buffer[name].tobytes() == y.buffer[name].tobytes(), name
        for part in ("actor", "actor_target", "critic", "critic_target"):
            sx, sy = getattr(x, part).state_dict(), getattr(y, part).state_dict()
            assert all(torch.equal(sx[k], sy[k]) for k in sx), part
        assert [(e.episode, e.end_step, e.length, e.terminated, e.returns.tobytes()) for e in x.episodes] == [
            (e.episode, e.end_step, e.length, e.terminated, e.returns.tobytes()) for e in y.episodes
        ]


@pytest.fixture
def one_thread():
    """One torch thread, as the `mapex` command uses by default (two threads on a busy 2-core
    machine make these tiny updates many times slower)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.mark.parametrize(("device", "graphs"), DEVICES)
def test_a_run_restored_from_a_checkpoint_ends_as_the_uninterrupted_one(device, graphs, one_thread):
    """The library: two stacked specialists, checkpointed mid-episode; runs restored from the
    checkpoint at step 70 (random actions, ring filling) and 210 (learning, ring wrapped) end
    bitwise as the run that was never stopped (on CUDA: within assert_close_results; with
    graphs, the restore captures them first and then fills the optimizers' state in place)."""
    jobs = [(0, 0), (0, 1)]
    saved: dict[int, bytes] = {}

    def keep(run) -> None:
        assert (run.ep_step > 0).any()  # some env is mid-episode
        buf = io.BytesIO()
        torch.save(run.state_dict(), buf)
        saved[run.t] = buf.getvalue()

    due = [lambda run: keep(run) if run.checkpoint_due() else None]
    reference = run_to_end(hopper_run(jobs, device, graphs), due).results()
    assert sorted(saved) == [70, 140, 210, 280]
    for t in (70, 210):
        run = hopper_run(jobs, device, graphs)
        run.load_state_dict(torch.load(io.BytesIO(saved[t]), weights_only=True))
        assert run.t == t
        (assert_same_results if device == "cpu" else assert_close_results)(
            run_to_end(run, fresh=False).results(), reference
        )
    # a state never fits a run of other specialists
    with pytest.raises(ValueError, match="specialists"):
        hopper_run([(1, 0), (1, 1)]).load_state_dict(torch.load(io.BytesIO(saved[70]), weights_only=True))


class Killed(Exception):
    """Stands for the worker dying: raised from inside the training loop."""


class StepCounter:
    """The env steps each training run takes, one entry per run in order (`counts`); while
    `die_at` is set, the run whose first specialist has objective `objective` dies before
    its step die_at."""

    def __init__(self, die_at: int | None, objective: int) -> None:
        self.die_at, self.objective = die_at, objective
        self.runs: list = []
        self.counts: list[int] = []

    def clear(self) -> None:
        """Disarm and start counting afresh."""
        self.die_at = None
        self.runs.clear()
        self.counts.clear()


def count_steps(monkeypatch, die_at: int | None = None, objective: int = 0) -> StepCounter:
    counter = StepCounter(die_at, objective)
    real = SpecialistsRun.step

    def step(self):
        if self.t == counter.die_at and self.jobs[0][1] == counter.objective:
            raise Killed(f"killed before step {counter.die_at}")
        if not counter.runs or counter.runs[-1] is not self:
            counter.runs.append(self)
            counter.counts.append(0)
        counter.counts[-1] += 1
        return real(self)

    monkeypatch.setattr(SpecialistsRun, "step", step)
    return counter


def run_stage(cli, d: Path, write_params, train_specialist=None, td3=None):
    """The stage in-process on the RESUME preset, its train_specialist and td3 sections updated."""
    params = write_params(
        d,
        {
            "env": RESUME["env"],
            "td3": {**RESUME["td3"], **(td3 or {})},
            "train_specialist": {**RESUME["train_specialist"], **(train_specialist or {})},
        },
    )
    return cli("train-specialist", "--seed", 0, "--out", d / "out", "--params", params)


def assert_same_artifacts(a: Path, b: Path) -> None:
    for k in (0, 1):
        x, _ = load_buffer(a / f"obj{k}" / "buffer.zarr")
        y, _ = load_buffer(b / f"obj{k}" / "buffer.zarr")
        for name in FIELDS:
            assert x[name].tobytes() == y[name].tobytes(), (k, name)
        sx, sy = state_dicts(a / f"obj{k}"), state_dicts(b / f"obj{k}")
        assert sx.keys() == sy.keys()
        for key in sx:
            assert torch.equal(sx[key], sy[key]), (k, key)
        assert (a / f"obj{k}" / "returns.csv").read_text() == (b / f"obj{k}" / "returns.csv").read_text()
        # keep-best (when on): the same kept step, score and checks
        ka, kb = (torch_load_checked(d / f"obj{k}" / "policy.pt", POLICY_FORMAT, 1)["meta"] for d in (a, b))
        assert ka.get("keep_best") == kb.get("keep_best"), k
        csv_a, csv_b = a / f"obj{k}" / "keep_best.csv", b / f"obj{k}" / "keep_best.csv"
        assert csv_a.exists() == csv_b.exists() == ("keep_best" in ka), k
        if csv_a.exists():
            assert csv_a.read_text() == csv_b.read_text()


@pytest.mark.parametrize(
    ("batched", "objective", "die_at", "resumed_at", "checkpoint", "keep_best_every"),
    [
        (True, 0, 250, 210, "specialist_state_obj0-obj1.pt", 0),
        (False, 1, 150, 140, "specialist_state_obj1.pt", 0),
        (True, 0, 250, 210, "specialist_state_obj0-obj1.pt", 40),
    ],
    ids=["stacked", "one-at-a-time", "stacked-keep-best"],
)
def test_killed_stage_resumes_to_identical_artifacts(
    batched, objective, die_at, resumed_at, checkpoint, keep_best_every, tmp_path, write_params, cli, monkeypatch
):
    """The stage dies between two checkpoints; the rerun resumes from the last one, takes
    only the steps left, ends with the same bytes as a run never stopped, and removes the
    checkpoint. One at a time: it dies in the second specialist, after the first was saved.
    Keep-best: checks at 120, 160 and 200 precede the checkpoint, 240, 280 and 300 follow it."""
    overrides = {"batched": batched, "keep_best_every": keep_best_every}
    ref = run_stage(cli, tmp_path / "ref", write_params, overrides)
    assert ref.exit_code == 0, ref.stderr
    counter = count_steps(monkeypatch, die_at, objective)
    dead = run_stage(cli, tmp_path / "run", write_params, overrides)
    assert isinstance(dead.exception, Killed)
    out = tmp_path / "run" / "out"
    ckpt_dir = tmp_path / "run" / ".out.resume"  # beside OUT: DVC deletes OUT itself before a rerun
    assert (ckpt_dir / checkpoint).is_file()
    assert not (out / f"obj{objective}").exists()  # nothing of the dying specialists was written
    counter.clear()
    again = run_stage(cli, tmp_path / "run", write_params, overrides)
    assert again.exit_code == 0, again.stderr
    assert f"resuming from step {resumed_at} of {ckpt_dir / checkpoint}" in again.stderr
    # stacked: one run, resumed; one at a time: obj0 trained again from 0, obj1 resumed
    assert counter.counts == ([300 - resumed_at] if batched else [300, 300 - resumed_at])
    assert_same_artifacts(tmp_path / "ref" / "out", out)
    assert sorted(p.name for p in out.iterdir()) == ["obj0", "obj1"] and not ckpt_dir.exists()  # the checkpoint is gone


@pytest.mark.parametrize(("device", "graphs"), DEVICES)
def test_sigkilled_stage_resumes_from_shared_storage(device, graphs, tmp_path, write_params):
    """A real kill: the `mapex` process gets SIGKILL as soon as its first checkpoint is on
    disk, on shared storage ($MAPEX_RESUME_ROOT, as a sweep sets it); the rerun, from another
    working directory as a retry on another node, resumes and ends with the bytes of a run
    never stopped (on CUDA: within the tolerance of assert_close_results)."""
    root = Path(__file__).resolve().parents[1]
    ts = {**RESUME["train_specialist"], "total_steps": 1000, "device": device}
    td3 = {**RESUME["td3"], "cuda_graphs": graphs}
    params = write_params(tmp_path, {"env": RESUME["env"], "td3": td3, "train_specialist": ts})
    env = {**os.environ, "PYTHONPATH": str(root), "OMP_NUM_THREADS": "1"}
    shared = {**env, "MAPEX_RESUME_ROOT": str(tmp_path / "shared")}

    def command(out: Path) -> list[str]:
        return [
            sys.executable,
            "-m",
            "stages.cli",
            "train-specialist",
            "--seed",
            "0",
            "--out",
            str(out),
            "--params",
            str(params),
        ]

    for d in ("ref", "node_a", "node_b"):
        (tmp_path / d).mkdir()
    ref = subprocess.run(
        command(tmp_path / "ref" / "out"), cwd=tmp_path / "ref", env=env, capture_output=True, text=True, timeout=300
    )
    assert ref.returncode == 0, ref.stderr[-3000:]
    out = tmp_path / "run" / "out"
    ckpt = tmp_path / "shared" / "out" / "specialist_state_obj0-obj1.pt"
    proc = subprocess.Popen(command(out), cwd=tmp_path / "node_a", env=shared, stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    while not ckpt.exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.005)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert ckpt.exists(), "the run ended before it could be killed mid-way"
    t = torch.load(ckpt, weights_only=True)["state"]["counters"]["t"]
    assert 70 <= t < 1000 and t % 70 == 0
    assert not (out / "obj0").exists() and not (out / "obj1").exists()
    again = subprocess.run(
        command(out), cwd=tmp_path / "node_b", env=shared, capture_output=True, text=True, timeout=300
    )
    assert again.returncode == 0, again.stderr[-3000:]
    assert f"resuming from step {t} of {ckpt}" in again.stderr
    if device == "cpu":
        assert_same_artifacts(tmp_path / "ref" / "out", out)
    else:
        for k in (0, 1):
            sx, sy = state_dicts(tmp_path / "ref" / "out" / f"obj{k}"), state_dicts(out / f"obj{k}")
            assert sx.keys() == sy.keys()
            for key in sx:
                torch.testing.assert_close(sx[key], sy[key], rtol=1e-4, atol=1e-5)
    assert not ckpt.parent.exists()  # no checkpoint left, nor a half-written one (its directory goes too)
    assert sorted(p.name for p in out.iterdir()) == ["obj0", "obj1"]


@pytest.mark.parametrize(
    ("objectives", "processes", "batched", "expected"),
    [
        ([0, 1], 1, True, [[[0, 1]]]),
        ([0, 1], 2, True, [[[0]], [[1]]]),
        ([0, 1], 5, True, [[[0]], [[1]]]),  # at most one process per objective
        ([0, 1, 2], 2, True, [[[0, 1]], [[2]]]),
        ([0, 1, 2], 2, False, [[[0], [1]], [[2]]]),
        ([1], 2, True, [[[1]]]),
    ],
)
def test_plan_splits_objectives_into_contiguous_parts(objectives, processes, batched, expected):
    from stages.train_specialist import plan

    cfg = RESUME_CFG.model_copy(update={"processes": processes, "batched": batched})
    assert plan(objectives, cfg) == expected


@pytest.mark.parametrize("keep_best_every", [0, 40], ids=["final", "keep-best"])
def test_side_by_side_processes_give_the_one_at_a_time_bits(keep_best_every, tmp_path, write_params, cli):
    """processes: 2 trains each specialist alone in its own worker process: the same bytes as
    batched: false, which trains them alone one after another in the stage's process (with
    keep-best: the same kept actors and checks too)."""
    ref = run_stage(cli, tmp_path / "ref", write_params, {"batched": False, "keep_best_every": keep_best_every})
    assert ref.exit_code == 0, ref.stderr
    two = run_stage(cli, tmp_path / "two", write_params, {"processes": 2, "keep_best_every": keep_best_every})
    assert two.exit_code == 0, two.stderr
    assert_same_artifacts(tmp_path / "ref" / "out", tmp_path / "two" / "out")
    assert sorted(p.name for p in (tmp_path / "two" / "out").iterdir()) == ["obj0", "obj1"]


@pytest.mark.slow  # worker processes killed and resumed (35-45 s): slow keeps `make test` within 8 min
def test_sigkilled_stage_stops_its_workers_and_resumes_them(tmp_path, write_params):
    """processes: 2, and the `mapex` process gets SIGKILL once both workers have checkpointed:
    the workers stop too (nothing is written after the kill), and the rerun resumes both to
    the bytes of a run never stopped."""
    root = Path(__file__).resolve().parents[1]
    ts = {**RESUME["train_specialist"], "total_steps": 2000, "checkpoint_every": 400, "processes": 2}
    params = write_params(tmp_path, {"env": RESUME["env"], "td3": RESUME["td3"], "train_specialist": ts})
    env = {**os.environ, "PYTHONPATH": str(root), "OMP_NUM_THREADS": "1"}

    def command(out: Path) -> list[str]:
        return [
            sys.executable,
            "-m",
            "stages.cli",
            "train-specialist",
            "--seed",
            "0",
            "--out",
            str(out),
            "--params",
            str(params),
        ]

    ref = subprocess.run(command(tmp_path / "ref"), cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert ref.returncode == 0, ref.stderr[-3000:]
    out = tmp_path / "run"
    ckpts = [
        tmp_path / ".run.resume" / "specialist_state_obj0.pt",
        tmp_path / ".run.resume" / "specialist_state_obj1.pt",
    ]
    proc = subprocess.Popen(command(out), cwd=tmp_path, env=env, stderr=subprocess.DEVNULL)
    deadline = time.time() + 300
    while not all(c.exists() for c in ckpts) and proc.poll() is None and time.time() < deadline:
        time.sleep(0.005)
    workers = children(proc.pid)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert all(c.exists() for c in ckpts), "the run ended before it could be killed mid-way"
    assert len(workers) >= 2  # the two workers (and multiprocessing's resource tracker)
    deadline = time.time() + 20
    while time.time() < deadline and any(alive(w) for w in workers):
        time.sleep(0.05)
    assert not any(alive(w) for w in workers), "a worker outlived the killed stage"
    steps = [torch.load(c, weights_only=True)["state"]["counters"]["t"] for c in ckpts]
    assert all(400 <= t < 2000 for t in steps)
    again = subprocess.run(command(out), cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr[-3000:]
    for c, t in zip(ckpts, steps):
        assert f"resuming from step {t} of {c}" in again.stderr
    assert_same_artifacts(tmp_path / "ref", out)
    assert sorted(p.name for p in out.iterdir()) == ["obj0", "obj1"]


def stage_command(out: Path, params: Path) -> list[str]:
    return [
        sys.executable,
        "-m",
        "stages.cli",
        "train-specialist",
        "--seed",
        "0",
        "--out",
        str(out),
        "--params",
        str(params),
    ]


SIGTERM_LINE = re.compile(
    r"train_specialist seed 0, (?P<what>obj .+): SIGTERM: checkpoint written at step (?P<t>\d+) "
    r"\((?P<path>.+)\); rerun to resume"
)


def sigterm_lines(stderr: str) -> list[re.Match]:
    return [m for m in map(SIGTERM_LINE.fullmatch, stderr.splitlines()) if m]


def test_sigterm_checkpoints_at_once_and_the_rerun_resumes(tmp_path, write_params):
    """SIGTERM (a scheduler's warning before it kills) once the first periodic checkpoint is
    on disk: the stage checkpoints after the step it is in, not at the next periodic one,
    says where in one line and exits with 143; the rerun resumes from that step and ends with
    the bytes of a run never stopped."""
    ts = {**RESUME["train_specialist"], "total_steps": 600}
    params = write_params(tmp_path, {"env": RESUME["env"], "td3": RESUME["td3"], "train_specialist": ts})
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1]), "OMP_NUM_THREADS": "1"}
    ref = subprocess.run(
        stage_command(tmp_path / "ref", params), cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300
    )
    assert ref.returncode == 0, ref.stderr[-3000:]
    out, ckpt = tmp_path / "run", tmp_path / ".run.resume" / "specialist_state_obj0-obj1.pt"
    proc = subprocess.Popen(stage_command(out, params), cwd=tmp_path, env=env, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 300
    while not ckpt.exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.005)
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 143, stderr[-3000:]
    assert "Traceback" not in stderr
    (line,) = sigterm_lines(stderr)
    t = int(line["t"])
    assert line["path"] == str(ckpt) and line["what"].startswith("obj 0 (") and ", obj 1 (" in line["what"]
    assert torch.load(ckpt, weights_only=True)["state"]["counters"]["t"] == t
    assert 70 <= t < 600
    assert not (out / "obj0").exists() and not (out / "obj1").exists()
    again = subprocess.run(
        stage_command(out, params), cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300
    )
    assert again.returncode == 0, again.stderr[-3000:]
    assert f"resuming from step {t} of {ckpt}" in again.stderr
    assert_same_artifacts(tmp_path / "ref", out)
    assert not ckpt.parent.exists()


@pytest.mark.slow  # worker processes killed and resumed (35-45 s): slow keeps `make test` within 8 min
def test_sigterm_is_passed_on_to_the_workers_and_each_checkpoints(tmp_path, write_params):
    """processes: 2, SIGTERM to the stage process alone once both workers have checkpointed:
    it passes it on, each worker checkpoints after its current step and says so, the stage
    exits with 143 once both have, and the rerun resumes both to the bytes of a run never stopped."""
    ts = {**RESUME["train_specialist"], "total_steps": 700, "checkpoint_every": 150, "processes": 2}
    params = write_params(tmp_path, {"env": RESUME["env"], "td3": RESUME["td3"], "train_specialist": ts})
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1]), "OMP_NUM_THREADS": "1"}
    ref = subprocess.run(
        stage_command(tmp_path / "ref", params), cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300
    )
    assert ref.returncode == 0, ref.stderr[-3000:]
    out = tmp_path / "run"
    ckpts = [tmp_path / ".run.resume" / f"specialist_state_obj{k}.pt" for k in (0, 1)]
    proc = subprocess.Popen(stage_command(out, params), cwd=tmp_path, env=env, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 300
    while not all(c.exists() for c in ckpts) and proc.poll() is None and time.time() < deadline:
        time.sleep(0.005)
    workers = children(proc.pid)
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 143, stderr[-3000:]
    assert "Traceback" not in stderr
    lines = sigterm_lines(stderr)
    assert [m["what"].split(" (")[0] for m in lines] == ["obj 0", "obj 1"], stderr[-3000:]
    assert [m["path"] for m in lines] == [str(c) for c in ckpts]
    steps = [int(m["t"]) for m in lines]
    assert [torch.load(c, weights_only=True)["state"]["counters"]["t"] for c in ckpts] == steps
    assert all(150 <= t < 700 for t in steps), stderr[-3000:]
    deadline = time.time() + 20  # multiprocessing's resource tracker ends once its pipe closes
    while time.time() < deadline and any(alive(w) for w in workers):
        time.sleep(0.05)
    assert not any(alive(w) for w in workers), "a worker outlived the stopped stage"
    again = subprocess.run(
        stage_command(out, params), cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300
    )
    assert again.returncode == 0, again.stderr[-3000:]
    for c, t in zip(ckpts, steps):
        assert f"resuming from step {t} of {c}" in again.stderr
    assert_same_artifacts(tmp_path / "ref", out)


def test_a_full_disk_stops_the_stage_with_one_line_and_keeps_the_old_artifacts(cheetah, tmp_path, write_params):
    """The stage rerun over its outputs with a file-size limit below an artifact's size (as a
    full disk or quota fails a write): exit 2, one line naming the file, the earlier
    artifacts byte for byte as they were, no temporary left."""
    import resource
    import shutil

    out = tmp_path / "out"
    shutil.copytree(cheetah.out.parent, out)
    before = {p: p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}
    params = write_params(tmp_path)

    def limited() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # so write() fails with EFBIG instead
        resource.setrlimit(resource.RLIMIT_FSIZE, (8192, 8192))

    cmd = [*stage_command(out, params), "--objective", "1"]
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1]), "OMP_NUM_THREADS": "1"}
    r = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300, preexec_fn=limited)
    assert r.returncode == 2, r.stderr[-3000:]
    assert "Traceback" not in r.stderr
    (line,) = error_lines(r.stderr)
    assert re.fullmatch(
        rf"error: {re.escape(str(out))}/obj1/(buffer\.zarr|policy\.pt|critics\.pt): cannot be written: the disk "
        r"is full or a quota or file-size limit was reached \(File too large\); the previous \S+ is left intact; "
        r"free some space and rerun",
        line,
    ), line
    assert {p: p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()} == before


def children(pid: int) -> list[int]:
    """The processes whose parent is `pid` (Linux /proc)."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if int(fields[1]) == pid:
            found.append(int(stat.parent.name))
    return found


def alive(pid: int) -> bool:
    """Running, and not a zombie waiting to be reaped."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


def test_changed_params_start_over_instead_of_resuming(tmp_path, write_params, cli, monkeypatch):
    """A checkpoint written under other params is not resumed: the run trains from step 0,
    (with checkpoint_every 0) saves no checkpoint of its own, and removes the stale one and
    those of other groupings of the objectives it trained."""
    import stages.train_specialist as stage

    counter = count_steps(monkeypatch, die_at=150)
    dead = run_stage(cli, tmp_path, write_params)
    assert isinstance(dead.exception, Killed)
    ckpt = tmp_path / ".out.resume" / "specialist_state_obj0-obj1.pt"
    assert ckpt.is_file()
    stale = tmp_path / ".out.resume" / "specialist_state_obj1.pt"  # as if left by a batched: false run
    stale.write_bytes(b"old")
    foreign = tmp_path / ".out.resume" / "specialist_state_obj1-obj2.pt"  # objective 2 is not trained here: kept
    foreign.write_bytes(b"old")
    saves: list[int] = []
    monkeypatch.setattr(stage.Checkpoint, "save", lambda self, state: saves.append(state))
    counter.clear()
    changed = run_stage(cli, tmp_path, write_params, {"checkpoint_every": 0}, td3={"tau": 0.01})
    assert changed.exit_code == 0, changed.stderr
    assert "changed since it was written; starting over" in changed.stderr
    assert "resuming" not in changed.stderr
    assert counter.counts == [300] and saves == []
    assert not ckpt.exists() and not stale.exists()
    assert foreign.exists()


def test_unreadable_or_foreign_checkpoints_are_ignored(tmp_path):
    bad = tmp_path / "specialist_state_obj0.pt"
    said: list[str] = []

    def load_checkpoint(path, fp):
        return Checkpoint(path, fp, said.append).load()

    bad.write_bytes(b"not a zip file")
    assert load_checkpoint(bad, "fp") is None and "cannot be read" in said[-1]
    torch.save({"format": "something.else", "format_version": 1}, bad)
    assert load_checkpoint(bad, "fp") is None and "not a mapex.checkpoint" in said[-1]
    torch.save(
        {"format": CHECKPOINT_FORMAT, "format_version": CHECKPOINT_VERSION, "fingerprint": "old", "state": {}}, bad
    )
    assert load_checkpoint(bad, "fp") is None and "changed since it was written" in said[-1]
    assert load_checkpoint(bad, "old") == {}
    n = len(said)
    assert (
        load_checkpoint(tmp_path / "missing.pt", "fp") is None and len(said) == n
    )  # no checkpoint yet: nothing to say
