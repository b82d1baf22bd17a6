"""td3.shared_prefix_steps: the TD3 specialists of a seed fork from one TD3 trained on a mixed reward.

The library (SpecialistsRun with `mix`, `fork_state`) on the tiny preset's sizes: the prefix's
buffer holds the mixed reward as one more column; at the fork every specialist holds the
prefix's networks, buffer rows and counters; after it they train apart. The stage: the
specialists' buffers share their first rows, the frames on the progress bar are the seed's
real ones, the kept prefix is gone once the artifacts are written, and bad params stop in one line.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline.core.buffer import load_buffer
from pipeline.core.drive import run_to_end
from pipeline.core.envs import env_spec, make_env
from pipeline.params.td3 import TD3Params
from pipeline.params.train_specialist import TrainSpecialistParams, check_against_td3
from pipeline.specialists.td3_training import SpecialistsRun

ENV, CAP = "mo-halfcheetah-v5", 100
TD3 = {"learning_starts": 260, "buffer_size": 1000, "batch_size": 32, "hidden_sizes": [16, 16]}
PREFIX, TOTAL = 300, 340


def _run(cfg: TrainSpecialistParams, td3: TD3Params, jobs, **kw) -> SpecialistsRun:
    spec = env_spec(make_env(ENV, CAP), ENV, CAP)
    return SpecialistsRun([make_env(ENV, CAP) for _ in jobs], spec, td3, cfg, jobs, torch.device("cpu"), **kw)


@pytest.fixture(scope="module")
def prefix_and_fork():
    torch.set_num_threads(1)
    td3 = TD3Params(**TD3, shared_prefix_steps=PREFIX)
    cfg = TrainSpecialistParams(total_steps=TOTAL, device="cpu")
    weights = [0.25, 0.75]
    prefix = _run(cfg.model_copy(update={"total_steps": PREFIX}), td3, [(0, 2)], mix=weights)
    run_to_end(prefix)
    saved = prefix.state_dict()
    fork = _run(cfg, td3, [(0, 0), (0, 1)], fork_from=lambda: saved)
    fork.start()
    at_fork = fork.state_dict()
    while not fork.done:
        fork.step()
    fork.finish()
    return saved, at_fork, fork, weights


def test_the_prefix_trains_on_the_weighted_sum_of_the_rewards(prefix_and_fork):
    saved, _, _, weights = prefix_and_fork
    spec = env_spec(make_env(ENV, CAP), ENV, CAP)
    rows = saved["buffer"]["rows"][0, :PREFIX].numpy()
    col = spec.obs_dim + spec.act_dim
    rewards, mixed = rows[:, col : col + 2], rows[:, col + 2]
    np.testing.assert_allclose(mixed, rewards @ np.asarray(weights), rtol=1e-5, atol=1e-6)
    assert saved["counters"]["t"] == PREFIX


def test_at_the_fork_every_specialist_is_the_prefix(prefix_and_fork):
    saved, at_fork, _, _ = prefix_and_fork
    assert at_fork["counters"]["t"] == PREFIX and at_fork["counters"]["start"] == PREFIX
    assert at_fork["counters"]["n_updates"] == saved["counters"]["n_updates"] > 0
    for name, value in at_fork["nets"]["actor"].items():
        for s in range(2):
            torch.testing.assert_close(value[s], saved["nets"]["actor"][name][0], rtol=0, atol=0)
    # critics: each specialist holds the prefix's pairs of the two env objectives (4 of its 6 members)
    for name, value in at_fork["nets"]["critic"].items():
        prefix_value = saved["nets"]["critic"][name]
        assert value.shape[0] == 8 and prefix_value.shape[0] == 6
        for s in range(2):
            torch.testing.assert_close(value[4 * s : 4 * s + 4], prefix_value[:4], rtol=0, atol=0)
    rows, prefix_rows = at_fork["buffer"]["rows"], saved["buffer"]["rows"]
    assert rows.shape[-1] == prefix_rows.shape[-1] - 1
    spec = env_spec(make_env(ENV, CAP), ENV, CAP)
    col = spec.obs_dim + spec.act_dim + 2
    for s in range(2):
        torch.testing.assert_close(rows[s, :, :col], prefix_rows[0, :, :col], rtol=0, atol=0)
        torch.testing.assert_close(rows[s, :, col:], prefix_rows[0, :, col + 1 :], rtol=0, atol=0)
    assert all(e["returns"].shape[1] == 2 for e in at_fork["episodes"])


def test_after_the_fork_each_specialist_trains_its_own_objective(prefix_and_fork):
    saved, _, fork, _ = prefix_and_fork
    results = fork.results()
    assert [r.objective for r in results] == [0, 1]
    assert all(len(r.buffer["obs"]) == TOTAL for r in results)
    # the shared first rows, then each its own
    np.testing.assert_array_equal(results[0].buffer["obs"][:PREFIX], results[1].buffer["obs"][:PREFIX])
    assert not np.array_equal(results[0].buffer["action"][PREFIX:], results[1].buffer["action"][PREFIX:])
    a0, a1 = (dict(r.actor.named_parameters()) for r in results)
    assert any(not torch.equal(a0[k], a1[k]) for k in a0)
    # only the steps after the fork are the specialists' own on the progress count
    assert fork.progress()[0] == (TOTAL - PREFIX) * 2


def test_a_forked_run_restored_from_its_checkpoint_goes_on_bitwise(prefix_and_fork):
    saved, at_fork, fork, _ = prefix_and_fork
    td3 = TD3Params(**TD3, shared_prefix_steps=PREFIX)
    cfg = TrainSpecialistParams(total_steps=TOTAL, device="cpu")
    again = _run(cfg, td3, [(0, 0), (0, 1)])
    again.load_state_dict(at_fork)
    assert again.start_step == PREFIX
    while not again.done:
        again.step()
    for a, b in zip(again.results(), fork.results()):
        np.testing.assert_array_equal(a.buffer["action"], b.buffer["action"])
        for (k, x), (_, y) in zip(a.actor.named_parameters(), b.actor.named_parameters()):
            assert torch.equal(x, y), k


def test_params_that_cannot_fork_are_refused():
    with pytest.raises(ValueError, match="needs secondary_critics"):
        TD3Params(**TD3, shared_prefix_steps=100, secondary_critics=False)
    with pytest.raises(ValueError, match="non-negative"):
        TD3Params(**TD3, shared_prefix_steps=100, shared_prefix_weights=[-1.0, 2.0])
    with pytest.raises(ValueError, match="shared_prefix_steps .* must be < train_specialist.total_steps"):
        check_against_td3(TrainSpecialistParams(total_steps=300), TD3Params(**TD3, shared_prefix_steps=300))
    # off (the default) leaves the section's dump as before the keys existed: old bits stay
    assert "shared_prefix_steps" not in TD3Params(**TD3).model_dump()
    assert TD3Params(**TD3, shared_prefix_steps=5).model_dump()["shared_prefix_steps"] == 5


@pytest.mark.integration
def test_stage_forks_every_specialist_from_one_prefix(tmp_path, write_params, mapex):
    params = write_params(tmp_path, {"td3": {"shared_prefix_steps": PREFIX}})
    out = tmp_path / "out"
    proc = mapex("train-specialist", "--seed", 0, "--out", out, "--params", params, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (b0, _), (b1, _) = load_buffer(out / "obj0" / "buffer.zarr"), load_buffer(out / "obj1" / "buffer.zarr")
    np.testing.assert_array_equal(b0["obs"][:PREFIX], b1["obs"][:PREFIX])
    np.testing.assert_array_equal(b0["reward"][:PREFIX], b1["reward"][:PREFIX])
    assert not np.array_equal(b0["action"][PREFIX:], b1["action"][PREFIX:])
    assert not any(p.name.startswith("specialist_") for p in tmp_path.rglob("*.pt")), "kept prefix left behind"
    (tmp_path / "bad").mkdir()
    bad = write_params(tmp_path / "bad", {"td3": {"shared_prefix_steps": PREFIX, "shared_prefix_weights": [1.0]}})
    proc = mapex("train-specialist", "--seed", 0, "--out", tmp_path / "bad" / "out", "--params", bad, cwd=tmp_path)
    assert proc.returncode == 2
    assert "td3.shared_prefix_weights" in proc.stderr and "expected 2" in proc.stderr
    assert not (tmp_path / "bad" / "out").exists()
