"""Stage train_specialist: the real `mapex train-specialist` command on the tiny preset.

Every artifact is reloaded through the real loaders and checked against the run's params;
bad params fail fast with one readable message and write nothing; same seed = same bits.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.artifacts import torch_load_checked
from pipeline.buffer import FIELDS, FORMAT, FORMAT_VERSION, load_buffer
from pipeline.checkpoint import CRITICS_FORMAT, POLICY_FORMAT, load_critics, load_policy
from pipeline.envs import env_spec, make_env
from pipeline.params.train_specialist import TrainSpecialistParams
from pipeline.specialist import train_specialist

CAP = 100  # the tiny preset's episode cap
TOTAL = 350  # its total_steps

# Hopper with a cap of 18 steps: at seed 0 some episodes fall (terminated) and some are cut by
# the cap (truncated); one even falls on its 18th step, so both flags are set there.
HOPPER = {"env": {"id": "mo-hopper-2obj-v5", "max_episode_steps": 18}, "train_specialist": {"secondary_critics": False}}


@dataclass
class Run:
    out: Path
    objective: int
    seed: int
    stderr: str


def train(tmp_path_factory, write_params, mapex, name: str, objective: int, seed: int, overrides=None) -> Run:
    d = tmp_path_factory.mktemp(name)
    params = write_params(d, overrides)
    proc = mapex("train-specialist", "--objective", objective, "--seed", seed, "--out", d / "out", "--params", params, cwd=d)
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
        "obs": (TOTAL, 17), "action": (TOTAL, 6), "reward": (TOTAL, 2), "next_obs": (TOTAL, 17),
        "terminated": (TOTAL,), "truncated": (TOTAL,), "episode": (TOTAL,), "episode_step": (TOTAL,),
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
    assert TrainSpecialistParams(**meta["params"]["train_specialist"]).total_steps == TOTAL
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
    assert torch_load_checked(hopper.out / "critics.pt", CRITICS_FORMAT, 1)["meta"]["params"]["train_specialist"][
        "secondary_critics"
    ] is False


# --- determinism --------------------------------------------------------------------------


def state_dicts(out: Path) -> dict[str, torch.Tensor]:
    pol = torch_load_checked(out / "policy.pt", POLICY_FORMAT, 1)
    cri = torch_load_checked(out / "critics.pt", CRITICS_FORMAT, 1)
    flat = {}
    for part, sd in (("actor", pol["actor"]), ("actor_target", pol["actor_target"]), ("online", cri["online"]), ("target", cri["target"])):
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


# --- failures -----------------------------------------------------------------------------


def error_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.startswith("error:")]


BAD_PARAMS = [
    ({"train_specialist": {"gamma": 1.5}}, ["train_specialist.gamma = 1.5", "less than 1"]),
    ({"train_specialist": {"batch_sizee": 64}}, ["train_specialist.batch_sizee", "unknown key"]),
    ({"train_specialist": {"learning_starts": 32}}, ["learning_starts (32) must be >= batch_size (64)"]),
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
    ("overrides", "expected"), BAD_PARAMS, ids=["out-of-range", "unknown-key", "cross-field", "env-section", "top-level", "env-id"]
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


def test_missing_params_file_is_a_clear_error(tmp_path, cli):
    result = cli("train-specialist", "--objective", 0, "--out", tmp_path / "out", "--params", tmp_path / "nope.yaml")
    check_failure(result.exit_code, result.stderr, [])
    assert error_lines(result.stderr) == [f"error: {tmp_path / 'nope.yaml'}: params file not found"]
    assert not (tmp_path / "out").exists()


# --- the training loop in-process ---------------------------------------------------------


def test_update_schedule_and_episode_records(monkeypatch):
    """Updates start at learning_starts, one per step; every policy_freq-th one moves the actor."""
    import pipeline.specialist as specialist_mod

    calls: list[bool] = []
    real_update = specialist_mod.stacked_update

    def counting_update(state, batch, noise, update_actor, **kw):
        calls.append(update_actor)
        assert batch.obs.shape == (1, 8, 8) and noise.shape == (1, 8, 2)
        return real_update(state, batch, noise, update_actor, **kw)

    monkeypatch.setattr(specialist_mod, "stacked_update", counting_update)
    cfg = TrainSpecialistParams(total_steps=40, learning_starts=30, batch_size=8, hidden_sizes=[4], buffer_size=100, policy_freq=3)
    env = make_env("mo-swimmer-v5", 15)
    spec = env_spec(env, "mo-swimmer-v5", 15)
    seen: list[tuple[int, int | None]] = []
    result = train_specialist(env, spec, cfg, 0, 0, torch.device("cpu"), on_step=lambda t, r: seen.append((t, r and r.episode)))
    env.close()
    assert calls == [False, False, True] * 3 + [False]
    assert [t for t, _ in seen] == list(range(1, 41))
    assert [(t, e) for t, e in seen if e is not None] == [(15, 0), (30, 1)]
    assert [(r.end_step, r.length, r.terminated) for r in result.episodes] == [(15, 15, False), (30, 15, False)]
    assert len(result.buffer["obs"]) == 40


def test_out_of_range_objective_in_the_core():
    env = make_env("mo-swimmer-v5", 15)
    spec = env_spec(env, "mo-swimmer-v5", 15)
    cfg = TrainSpecialistParams(total_steps=40, learning_starts=30, batch_size=8, hidden_sizes=[4])
    with pytest.raises(ValueError, match="objective 5 out of range"):
        train_specialist(env, spec, cfg, 5, 0, torch.device("cpu"))
    env.close()
