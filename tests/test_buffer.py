"""Replay buffer ring, its Zarr artifact (round trip, chunking, damage detection) and atomic writes."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
import zarr
from hypothesis import given
from hypothesis import strategies as st

import pipeline.core.buffer as buffer_mod
from pipeline.core.artifacts import ArtifactError, atomic_path, torch_load_checked, torch_save_atomic, write_text_atomic
from pipeline.core.buffer import FIELDS, FORMAT, FORMAT_VERSION, ReplayBuffer, batch_at, load_buffer, save_buffer

OBS, ACT, NOBJ = 3, 2, 2
ATTRS = {
    "env_id": "mo-test-v0",
    "objective": 1,
    "seed": 7,
    "obs_dim": OBS,
    "act_dim": ACT,
    "n_objectives": NOBJ,
    "max_episode_steps": 4,
}


def fill(buf: ReplayBuffer, n: int) -> None:
    """Add n rows whose every field encodes the row number i (episodes of 4 steps)."""
    for i in range(n):
        buf.add(
            obs=np.full(OBS, i, np.float32),
            action=np.full(ACT, i, np.float32),
            reward=np.array([i, -i], np.float32),
            next_obs=np.full(OBS, i + 1, np.float32),
            terminated=False,
            truncated=i % 4 == 3,
            episode=i // 4,
            step=i % 4,
        )


def random_data(n: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {
        "obs": rng.standard_normal((n, OBS)).astype(np.float32),
        "action": rng.uniform(-1, 1, (n, ACT)).astype(np.float32),
        "reward": rng.standard_normal((n, NOBJ)).astype(np.float32),
        "next_obs": rng.standard_normal((n, OBS)).astype(np.float32),
        "terminated": rng.random(n) < 0.2,
        "truncated": rng.random(n) < 0.2,
        "episode": np.arange(n, dtype=np.int64) // 3,
        "episode_step": (np.arange(n) % 3).astype(np.int32),
    }


# --- the in-RAM ring ----------------------------------------------------------------------


def test_ring_below_capacity_keeps_insertion_order():
    buf = ReplayBuffer(5, OBS, ACT, NOBJ)
    fill(buf, 3)
    chron = buf.chronological()
    assert buf.size == 3 and buf.ptr == 3
    assert chron["obs"][:, 0].tolist() == [0, 1, 2]


def test_ring_wraps_and_unrolls_oldest_first():
    buf = ReplayBuffer(4, OBS, ACT, NOBJ)
    fill(buf, 6)  # rows 0, 1 overwritten by 4, 5
    assert buf.size == 4 and buf.ptr == 2
    assert buf.data["obs"][:, 0].tolist() == [4, 5, 2, 3]  # raw storage
    chron = buf.chronological()
    assert chron["obs"][:, 0].tolist() == [2, 3, 4, 5]
    assert chron["reward"].tolist() == [[2, -2], [3, -3], [4, -4], [5, -5]]
    assert chron["episode"].tolist() == [0, 0, 1, 1]
    assert chron["episode_step"].tolist() == [2, 3, 0, 1]
    assert chron["truncated"].tolist() == [False, True, False, False]


@given(capacity=st.integers(1, 9), n=st.integers(0, 30))
def test_ring_holds_the_last_capacity_rows_in_order(capacity, n):
    buf = ReplayBuffer(capacity, OBS, ACT, NOBJ)
    fill(buf, n)
    chron = buf.chronological()
    expected = list(range(max(0, n - capacity), n))
    for name in FIELDS:
        assert len(chron[name]) == len(expected)
    assert chron["obs"][:, 0].tolist() == expected
    assert chron["next_obs"][:, 0].tolist() == [i + 1 for i in expected]
    assert chron["episode"].tolist() == [i // 4 for i in expected]


def test_sample_draws_stored_rows_as_a_typed_batch():
    buf = ReplayBuffer(10, OBS, ACT, NOBJ)
    fill(buf, 6)
    batch = buf.sample(50, np.random.default_rng(0), torch.device("cpu"))
    assert batch.obs.shape == (50, OBS) and batch.action.shape == (50, ACT)
    assert batch.reward.shape == (50, NOBJ) and batch.terminated.shape == (50,)
    assert batch.terminated.dtype == torch.float32
    rows = batch.obs[:, 0]
    assert rows.min() >= 0 and rows.max() <= 5
    # An unfilled row (6..9) holds zeros everywhere, so next_obs = obs + 1 also rules those out.
    assert torch.equal(batch.next_obs[:, 0], rows + 1)
    assert torch.equal(batch.reward[:, 0], rows) and torch.equal(batch.reward[:, 1], -rows)


def test_batch_at_picks_exactly_the_given_rows():
    data = random_data(8)
    data["terminated"][:] = [0, 1, 0, 0, 1, 0, 0, 0]
    idx = np.array([4, 1, 1, 6])
    b = batch_at(data, idx)
    assert torch.equal(b.obs, torch.from_numpy(data["obs"][idx]))
    assert torch.equal(b.reward, torch.from_numpy(data["reward"][idx]))
    assert b.terminated.tolist() == [1.0, 1.0, 1.0, 0.0]


# --- the Zarr artifact --------------------------------------------------------------------


def test_round_trip_is_bitwise(tmp_path):
    data = random_data(29)
    save_buffer(tmp_path / "b.zarr", data, ATTRS)
    loaded, attrs = load_buffer(tmp_path / "b.zarr")
    assert set(loaded) == set(FIELDS)
    for name in FIELDS:
        assert loaded[name].dtype == data[name].dtype, name
        assert loaded[name].shape == data[name].shape, name
        assert loaded[name].tobytes() == data[name].tobytes(), name
    for key, value in ATTRS.items():
        assert attrs[key] == value
    assert attrs["format"] == FORMAT and attrs["format_version"] == FORMAT_VERSION
    assert attrs["n_transitions"] == 29 and attrs["complete"] is True


def test_empty_buffer_round_trips(tmp_path):
    data = random_data(0)
    save_buffer(tmp_path / "b.zarr", data, ATTRS)
    loaded, attrs = load_buffer(tmp_path / "b.zarr")
    assert attrs["n_transitions"] == 0
    assert loaded["obs"].shape == (0, OBS)


def test_chunks_run_along_time_only(tmp_path, monkeypatch):
    monkeypatch.setattr(buffer_mod, "CHUNK_ROWS", 4)
    save_buffer(tmp_path / "b.zarr", random_data(10), ATTRS)
    group = zarr.open_group(str(tmp_path / "b.zarr"), mode="r")
    assert group["obs"].chunks == (4, OBS)
    assert group["reward"].chunks == (4, NOBJ)
    assert group["episode"].chunks == (4,)
    # 10 rows in chunks of 4 rows: 3 chunk files, each holding every column.
    chunk_files = sorted(
        p.relative_to(tmp_path / "b.zarr" / "obs").as_posix()
        for p in (tmp_path / "b.zarr" / "obs" / "c").rglob("*")
        if p.is_file()
    )
    assert chunk_files == ["c/0/0", "c/1/0", "c/2/0"]
    loaded, _ = load_buffer(tmp_path / "b.zarr")
    assert loaded["obs"].shape == (10, OBS)


def test_chunk_rows_default_is_large_for_small_buffers(tmp_path):
    save_buffer(tmp_path / "b.zarr", random_data(10), ATTRS)
    assert zarr.open_group(str(tmp_path / "b.zarr"), mode="r")["obs"].chunks == (10, OBS)


def test_save_rejects_fields_of_unequal_length(tmp_path):
    data = random_data(5)
    data["reward"] = data["reward"][:4]
    with pytest.raises(ValueError, match="reward"):
        save_buffer(tmp_path / "b.zarr", data, ATTRS)
    assert not (tmp_path / "b.zarr").exists()


@pytest.fixture
def saved(tmp_path, monkeypatch):
    """A 10-row buffer in chunks of 4 rows; returns its path."""
    monkeypatch.setattr(buffer_mod, "CHUNK_ROWS", 4)
    path = tmp_path / "b.zarr"
    save_buffer(path, random_data(10), ATTRS)
    return path


def edit_attrs(path, change) -> None:
    meta_file = path / "zarr.json"
    meta = json.loads(meta_file.read_text())
    change(meta["attributes"])
    meta_file.write_text(json.dumps(meta))


def test_missing_chunk_is_caught_by_checksum(saved):
    (saved / "obs" / "c" / "1" / "0").unlink()  # Zarr would read the rows as zeros
    with pytest.raises(ArtifactError) as info:
        load_buffer(saved)
    assert str(saved) in str(info.value)
    assert "'obs'" in str(info.value) and "checksum" in str(info.value)


def test_damaged_chunk_is_caught(saved):
    chunk = saved / "next_obs" / "c" / "0" / "0"
    raw = bytearray(chunk.read_bytes())
    raw[-1] ^= 0xFF
    chunk.write_bytes(bytes(raw))
    with pytest.raises(ArtifactError, match=str(saved)):
        load_buffer(saved)


def test_missing_array_is_caught(saved):
    shutil.rmtree(saved / "action")
    with pytest.raises(ArtifactError, match=r"array 'action' is missing or unreadable"):
        load_buffer(saved)


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        (lambda a: a.update(complete=False), "not completely written"),
        (lambda a: a.update(format_version=FORMAT_VERSION + 1), "format_version"),
        (lambda a: a.update(format="something.else"), "format is 'something.else'"),
        (lambda a: a.update(n_transitions=11), "attributes say 11"),
        (lambda a: a["checksums"].update(reward="00000000"), "'reward' fails its checksum"),
        (lambda a: a.update(obs_dim=OBS + 1), "expected \\(T, 4\\)"),
        (lambda a: a.pop("n_transitions"), "n_transitions"),
        (lambda a: a.pop("act_dim"), "act_dim"),
    ],
)
def test_inconsistent_attributes_are_caught(saved, change, expected):
    edit_attrs(saved, change)
    with pytest.raises(ArtifactError, match=expected) as info:
        load_buffer(saved)
    assert str(saved) in str(info.value)


def test_missing_buffer_is_an_artifact_error(tmp_path):
    with pytest.raises(ArtifactError, match="no Zarr group"):
        load_buffer(tmp_path / "absent.zarr")


def test_interrupted_save_leaves_no_destination(tmp_path, monkeypatch):
    def boom(_arr):
        raise RuntimeError("killed mid-write")

    monkeypatch.setattr(buffer_mod, "_crc", boom)  # fails after the arrays are written
    with pytest.raises(RuntimeError, match="killed"):
        save_buffer(tmp_path / "b.zarr", random_data(6), ATTRS)
    assert list(tmp_path.iterdir()) == []


def test_interrupted_overwrite_keeps_the_old_buffer(tmp_path, monkeypatch):
    path = tmp_path / "b.zarr"
    old = random_data(6, seed=1)
    save_buffer(path, old, ATTRS)
    monkeypatch.setattr(buffer_mod, "_crc", lambda arr: (_ for _ in ()).throw(RuntimeError("killed")))
    with pytest.raises(RuntimeError):
        save_buffer(path, random_data(9, seed=2), ATTRS)
    monkeypatch.undo()
    loaded, _ = load_buffer(path)
    assert loaded["obs"].tobytes() == old["obs"].tobytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.zarr"]


def test_overwrite_replaces_a_buffer(tmp_path):
    path = tmp_path / "b.zarr"
    save_buffer(path, random_data(6, seed=1), ATTRS)
    new = random_data(9, seed=2)
    save_buffer(path, new, ATTRS)
    loaded, attrs = load_buffer(path)
    assert attrs["n_transitions"] == 9 and loaded["obs"].tobytes() == new["obs"].tobytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.zarr"]


# --- atomic writes and checked torch loads ------------------------------------------------


def test_atomic_path_leaves_nothing_when_the_writer_raises(tmp_path):
    dest = tmp_path / "sub" / "out.txt"
    with pytest.raises(KeyError):
        with atomic_path(dest) as tmp:
            tmp.write_text("half")
            raise KeyError("writer failed")
    assert not dest.exists()
    assert list((tmp_path / "sub").iterdir()) == []


def test_atomic_path_keeps_an_existing_file_when_the_writer_raises(tmp_path):
    dest = tmp_path / "out.txt"
    write_text_atomic(dest, "old")
    with pytest.raises(KeyError):
        with atomic_path(dest) as tmp:
            tmp.write_text("new")
            raise KeyError("writer failed")
    assert dest.read_text() == "old"
    write_text_atomic(dest, "new")
    assert dest.read_text() == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]


def test_torch_load_checked_catches_truncation_and_wrong_format(tmp_path):
    path = tmp_path / "x.pt"
    torch_save_atomic({"format": "mapex.thing", "format_version": 3, "w": torch.arange(1000.0)}, path)
    assert torch.equal(torch_load_checked(path, "mapex.thing", 3)["w"], torch.arange(1000.0))
    with pytest.raises(ArtifactError, match="format_version 3, expected 4"):
        torch_load_checked(path, "mapex.thing", 4)
    with pytest.raises(ArtifactError, match="format is 'mapex.thing', expected 'mapex.other'"):
        torch_load_checked(path, "mapex.other", 3)
    path.write_bytes(path.read_bytes()[:200])
    with pytest.raises(ArtifactError, match="cannot be read as a torch checkpoint") as info:
        torch_load_checked(path, "mapex.thing", 3)
    assert str(path) in str(info.value)
    with pytest.raises(ArtifactError, match="file not found"):
        torch_load_checked(tmp_path / "absent.pt", "mapex.thing", 3)
