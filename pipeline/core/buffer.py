"""Replay buffer: an in-RAM ring used while training, saved as a Zarr v3 group.

Zarr layout (format "mapex.replay_buffer", version 1), T transitions in chronological order:

    obs           (T, obs_dim)       float32
    action        (T, act_dim)       float32
    reward        (T, n_objectives)  float32   full reward vector, every objective
    next_obs      (T, obs_dim)       float32
    terminated    (T,)               bool      true terminal state: no bootstrap
    truncated     (T,)               bool      time-limit cut: bootstrap through it
    episode       (T,)               int64     global episode index (contiguous runs)
    episode_step  (T,)               int32     step index inside its episode

Group attributes: format, format_version, env_id, objective, seed, obs_dim, act_dim,
n_objectives, n_transitions, max_episode_steps, complete, checksums (CRC32 of each array's
bytes, so a lost or damaged chunk, which Zarr would silently read as zeros, is caught). Arrays are chunked along time
only (CHUNK_ROWS rows a chunk), so a 1M-row buffer is a few dozen files.
"""

from __future__ import annotations

import zlib
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
import zarr

from pipeline.core.artifacts import ArtifactError, atomic_path

FORMAT = "mapex.replay_buffer"
FORMAT_VERSION = 1
CHUNK_ROWS = 131_072

FIELDS = ("obs", "action", "reward", "next_obs", "terminated", "truncated", "episode", "episode_step")


class Batch(NamedTuple):
    """A minibatch of transitions as tensors."""

    obs: torch.Tensor  # (B, obs_dim) float32
    action: torch.Tensor  # (B, act_dim) float32
    reward: torch.Tensor  # (B, n_objectives) float32
    next_obs: torch.Tensor  # (B, obs_dim) float32
    terminated: torch.Tensor  # (B,) float32, 1.0 where s' is terminal


class ReplayBuffer:
    """Fixed-capacity ring of transitions in numpy arrays; oldest rows are overwritten."""

    def __init__(self, capacity: int, obs_dim: int, act_dim: int, n_objectives: int):
        self.capacity = capacity
        self.data: dict[str, np.ndarray] = {
            "obs": np.zeros((capacity, obs_dim), np.float32),
            "action": np.zeros((capacity, act_dim), np.float32),
            "reward": np.zeros((capacity, n_objectives), np.float32),
            "next_obs": np.zeros((capacity, obs_dim), np.float32),
            "terminated": np.zeros(capacity, bool),
            "truncated": np.zeros(capacity, bool),
            "episode": np.zeros(capacity, np.int64),
            "episode_step": np.zeros(capacity, np.int32),
        }
        self.ptr = 0
        self.size = 0

    def add(self, obs, action, reward, next_obs, terminated: bool, truncated: bool, episode: int, step: int) -> None:
        i = self.ptr
        d = self.data
        d["obs"][i] = obs
        d["action"][i] = action
        d["reward"][i] = reward
        d["next_obs"][i] = next_obs
        d["terminated"][i] = terminated
        d["truncated"][i] = truncated
        d["episode"][i] = episode
        d["episode_step"][i] = step
        self.ptr = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def chronological(self) -> dict[str, np.ndarray]:
        """The stored rows, oldest first."""
        if self.size < self.capacity:
            return {k: v[: self.size] for k, v in self.data.items()}
        order = np.concatenate([np.arange(self.ptr, self.capacity), np.arange(0, self.ptr)])
        return {k: v[order] for k, v in self.data.items()}

    def sample(self, batch_size: int, rng: np.random.Generator, device: torch.device) -> Batch:
        idx = rng.integers(0, self.size, size=batch_size)
        return batch_at(self.data, idx, device)


def batch_at(data: dict[str, np.ndarray], idx: np.ndarray, device: torch.device | str = "cpu") -> Batch:
    """The rows `idx` of a buffer's arrays as a Batch on `device`."""

    def t(name: str) -> torch.Tensor:
        return torch.from_numpy(data[name][idx]).to(device)

    return Batch(t("obs"), t("action"), t("reward"), t("next_obs"), t("terminated").float())


def _crc(arr: np.ndarray) -> str:
    return f"{zlib.crc32(np.ascontiguousarray(arr).tobytes()):08x}"


def save_buffer(path: str | Path, data: dict[str, np.ndarray], attrs: dict[str, Any]) -> None:
    """Write transitions `data` (fields of FIELDS, equal length) as a Zarr v3 group, atomically."""
    n = len(data["obs"])
    for name in FIELDS:
        if len(data[name]) != n:
            raise ValueError(f"field {name} has {len(data[name])} rows, expected {n}")
    with atomic_path(path) as tmp:
        group = zarr.open_group(str(tmp), mode="w", zarr_format=3)
        for name in FIELDS:
            arr = np.ascontiguousarray(data[name])
            chunks = (min(CHUNK_ROWS, max(n, 1)), *arr.shape[1:])
            z = group.create_array(name, shape=arr.shape, dtype=arr.dtype, chunks=chunks)
            if n:
                z[...] = arr
        group.attrs.update(
            {
                **attrs,
                "format": FORMAT,
                "format_version": FORMAT_VERSION,
                "n_transitions": int(n),
                "complete": True,
                "checksums": {name: _crc(data[name]) for name in FIELDS},
            }
        )


def load_buffer(path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """`_load_buffer`, with MemoryError and RecursionError as the one-line refusal naming the path."""
    try:
        return _load_buffer(path)
    except MemoryError:
        raise ArtifactError(f"{path}: refused: reading it needed more memory than this process may use") from None
    except RecursionError:
        raise ArtifactError(f"{path}: refused: its metadata nests too deep") from None


def _load_buffer(path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read a replay buffer fully into RAM; returns (arrays, attributes).

    Raises ArtifactError naming the path if it is missing, not a mapex buffer, or truncated,
    or if obs, action, reward or next_obs hold a NaN or infinity (naming the array and the
    first such row): training on it would only spread it.
    """
    path = Path(path)
    if not (path / "zarr.json").is_file():
        raise ArtifactError(f"{path}: no Zarr group here (expected a {FORMAT} directory)")
    try:
        group = zarr.open_group(str(path), mode="r")
        attrs = dict(group.attrs)
    except Exception as exc:
        raise ArtifactError(f"{path}: cannot open as a Zarr group ({exc})") from None
    if attrs.get("format") != FORMAT:
        raise ArtifactError(f"{path}: format is {attrs.get('format')!r}, expected {FORMAT!r}")
    if attrs.get("format_version") != FORMAT_VERSION:
        raise ArtifactError(f"{path}: format_version {attrs.get('format_version')!r}, expected {FORMAT_VERSION}")
    if not attrs.get("complete"):
        raise ArtifactError(f"{path}: buffer was not completely written")
    missing = [k for k in ("n_transitions", "obs_dim", "act_dim", "n_objectives") if k not in attrs]
    if missing:
        raise ArtifactError(f"{path}: attribute(s) {missing} missing")
    n = attrs["n_transitions"]
    check_declared(path, attrs)  # shapes, dtypes, codecs and size, from the metadata, before any array is read
    data = {}
    for name in FIELDS:
        try:
            arr = group[name][...]
        except Exception as exc:
            raise ArtifactError(f"{path}: array {name!r} is missing or unreadable ({exc})") from None
        if len(arr) != n:
            raise ArtifactError(f"{path}: array {name!r} has {len(arr)} rows, attributes say {n}")
        if attrs.get("checksums", {}).get(name) != _crc(arr):
            raise ArtifactError(f"{path}: array {name!r} fails its checksum (a chunk is missing or damaged)")
        data[name] = arr
    expect = {
        "obs": attrs["obs_dim"],
        "next_obs": attrs["obs_dim"],
        "action": attrs["act_dim"],
        "reward": attrs["n_objectives"],
    }
    for name, dim in expect.items():
        if data[name].ndim != 2 or data[name].shape[1] != dim:
            raise ArtifactError(f"{path}: array {name!r} has shape {data[name].shape}, expected (T, {dim})")
        bad = first_nonfinite_row(data[name])
        if bad is not None:
            value = data[name][bad][~np.isfinite(data[name][bad])][0]
            what = "NaN" if np.isnan(value) else f"{value:+}"  # NaN, +inf or -inf
            raise ArtifactError(f"{path}: array {name!r} holds {what} in row {bad} (its values must be finite)")
    return data, attrs


# What a mapex buffer's arrays are (docs/artifacts.md): anything else in the metadata is refused
# before an array is read (issue 57: a 1.6 KB buffer declaring a huge shape made zarr allocate and
# fill 1 GiB before the shape check; a `pickle` codec was stopped only by zarr's dtype table).
DTYPES = {
    "obs": "float32", "action": "float32", "reward": "float32", "next_obs": "float32",
    "terminated": "bool", "truncated": "bool", "episode": "int64", "episode_step": "int32",
}  # fmt: skip
CODECS = ("bytes", "zstd", "blosc", "gzip", "crc32c", "transpose")
MAX_META_BYTES = 1 << 20  # an array's zarr.json is under 1 KB
# The budget: the arrays' declared bytes at most this allowance plus DECODE_RATIO times the bytes
# of the buffer's files (zstd level 0, the writer's codec, packs real transitions about 1.2-2x).
DECLARED_ALLOWANCE = 64 << 20
DECODE_RATIO = 64


def check_declared(path: Path, attrs: dict[str, Any]) -> None:
    """Refuse, in one line naming the buffer and the array, metadata a mapex buffer never holds:
    an array that is not one of FIELDS' dtypes and shapes ((n_transitions, dim) or
    (n_transitions,), the dims from the attributes), a codec outside CODECS, a chunk grid not
    along time, or declared bytes above DECLARED_ALLOWANCE + DECODE_RATIO x the files' bytes (an
    absurd shape over a few files). Reads only the small zarr.json files, so nothing is allocated
    for a declared shape before it is checked."""
    import json

    n = attrs.get("n_transitions")
    dims = {"obs": attrs.get("obs_dim"), "next_obs": attrs.get("obs_dim"), "action": attrs.get("act_dim")}
    dims["reward"] = attrs.get("n_objectives")
    if type(n) is not int or n < 0 or any(type(d) is not int or d < 1 for d in dims.values()):
        raise ArtifactError(f"{path}: attributes n_transitions, obs_dim, act_dim, n_objectives must be ints >= 0/1")
    declared = 0
    for name in FIELDS:
        meta_file = path / name / "zarr.json"
        try:
            size = meta_file.stat().st_size
            if size > MAX_META_BYTES:
                raise ArtifactError(f"{meta_file}: {size} bytes of metadata; refused above {MAX_META_BYTES}")
            meta = json.loads(meta_file.read_text())
        except ArtifactError:
            raise
        except Exception as exc:  # noqa: BLE001 - missing, unreadable or not JSON: one line
            raise ArtifactError(
                f"{path}: array {name!r} is missing or unreadable (no metadata: {type(exc).__name__})"
            ) from None
        want_shape = [n, dims[name]] if name in dims else [n]
        if not isinstance(meta, dict) or meta.get("node_type") != "array" or meta.get("zarr_format") != 3:
            raise ArtifactError(f"{meta_file}: not a Zarr v3 array")
        if meta.get("data_type") != DTYPES[name]:
            raise ArtifactError(f"{meta_file}: data_type {str(meta.get('data_type'))[:40]!r}, expected {DTYPES[name]}")
        if meta.get("shape") != want_shape:
            expected = f"(T, {dims[name]})" if name in dims else "(T,)"
            raise ArtifactError(
                f"{path}: array {name!r} declares shape {str(meta.get('shape'))[:60]}; the attributes say {n} rows, "
                f"expected {expected}"
            )
        codecs = meta.get("codecs")
        names = [c.get("name") if isinstance(c, dict) else c for c in codecs] if isinstance(codecs, list) else None
        if not names or any(c not in CODECS for c in names) or meta.get("storage_transformers") not in (None, []):
            raise ArtifactError(f"{meta_file}: codecs {str(names)[:80]}; a mapex buffer uses only {list(CODECS)}")
        grid = meta.get("chunk_grid") or {}
        chunk = (grid.get("configuration") or {}).get("chunk_shape") if isinstance(grid, dict) else None
        if grid.get("name") != "regular" or not isinstance(chunk, list) or chunk[1:] != want_shape[1:]:
            raise ArtifactError(f"{meta_file}: chunks {str(chunk)[:60]}; expected chunks along time only")
        if not (type(chunk[0]) is int and chunk[0] >= 1):
            raise ArtifactError(f"{meta_file}: chunk rows {chunk[0]!r}; expected an int >= 1")
        declared += n * (dims.get(name, 1)) * np.dtype(DTYPES[name]).itemsize
    on_disk = sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
    if declared > DECLARED_ALLOWANCE + DECODE_RATIO * on_disk:
        raise ArtifactError(
            f"{path}: arrays declare {declared} bytes from {on_disk} bytes of files; refused above "
            f"{DECLARED_ALLOWANCE} + {DECODE_RATIO} x the files (docs/trust.md)"
        )


def first_nonfinite_row(arr: np.ndarray, chunk: int = CHUNK_ROWS) -> int | None:
    """The index of the first row of `arr` (T, d) holding a NaN or infinity, else None
    (checked `chunk` rows at a time, so the check needs little memory beside the array)."""
    for start in range(0, len(arr), chunk):
        ok = np.isfinite(arr[start : start + chunk]).all(axis=1)
        if not ok.all():
            return start + int(np.argmin(ok))
    return None


class StackedReplay:
    """The replay buffers of S specialists trained in lockstep, resident on the training device.

    Every specialist adds one row per env step, so all S rings share one write pointer and
    one size. The fields an update reads (obs, action, reward, next_obs, terminated) are
    packed into one tensor `rows` (S, capacity, F) on the device: a row is written once (one
    host-to-device copy per step for all S specialists) and a minibatch is one gather, with
    no host-to-device copy per update. Bookkeeping fields an update never reads (truncated,
    episode, episode_step) stay in host arrays. `chronological(s)` gives specialist s's rows in
    the Zarr artifact's layout, so nothing downstream changes.
    """

    def __init__(self, n: int, capacity: int, obs_dim: int, act_dim: int, n_objectives: int, device: torch.device):
        self.n, self.capacity, self.device = n, capacity, torch.device(device)
        o, a, m = obs_dim, act_dim, n_objectives
        # column slices of the packed row: obs | action | reward | next_obs | terminated
        self.cols = {
            "obs": slice(0, o),
            "action": slice(o, o + a),
            "reward": slice(o + a, o + a + m),
            "next_obs": slice(o + a + m, 2 * o + a + m),
            "terminated": slice(2 * o + a + m, 2 * o + a + m + 1),
        }
        width = 2 * o + a + m + 1
        self.rows = torch.zeros(n, capacity, width, device=self.device)
        on_cuda = self.device.type == "cuda"
        # Staging row for all S specialists; pinned on CUDA so its copy does not block the host.
        # `_copied` marks the end of its last copy: the row is rewritten only after it.
        self._stage = torch.zeros(n, width, pin_memory=on_cuda) if on_cuda else None
        self._copied = torch.cuda.Event() if on_cuda else None
        self.host = {
            "truncated": np.zeros((n, capacity), bool),
            "episode": np.zeros((n, capacity), np.int64),
            "episode_step": np.zeros((n, capacity), np.int32),
        }
        self.ptr = 0
        self.size = 0

    def add(self, obs, action, reward, next_obs, terminated, truncated, episode, step) -> None:
        """Append one row per specialist: arrays with a leading S (obs (S, o), terminated (S,), ...)."""
        i = self.ptr
        if self._copied is not None:
            self._copied.synchronize()  # free when the step's action read has synced already
        stage = self._stage.numpy() if self._stage is not None else self.rows[:, i].numpy()
        c = self.cols
        stage[:, c["obs"]] = obs
        stage[:, c["action"]] = action
        stage[:, c["reward"]] = reward
        stage[:, c["next_obs"]] = next_obs
        stage[:, c["terminated"]] = np.asarray(terminated, np.float32)[:, None]
        if self._stage is not None:
            self.rows[:, i].copy_(self._stage, non_blocking=True)
            self._copied.record()
        self.host["truncated"][:, i] = truncated
        self.host["episode"][:, i] = episode
        self.host["episode_step"][:, i] = step
        self.ptr = (i + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def gather(self, idx: torch.Tensor) -> Batch:
        """Rows idx (S, B) long, on the device, of each specialist's ring -> Batch with a leading S."""
        got = torch.gather(self.rows, 1, idx.unsqueeze(-1).expand(-1, -1, self.rows.shape[2]))  # (S, B, F)
        c = self.cols
        return Batch(
            got[..., c["obs"]],
            got[..., c["action"]],
            got[..., c["reward"]],
            got[..., c["next_obs"]],
            got[..., c["terminated"]].squeeze(-1),
        )

    def take(self, s: int, idx: np.ndarray, name: str = "obs") -> np.ndarray:
        """Field `name` of specialist s's ring slots `idx` (storage positions), as numpy."""
        if name in self.host:
            return self.host[name][s][idx].copy()
        rows = self.rows[s, torch.from_numpy(np.asarray(idx, np.int64)).to(self.device), self.cols[name]].cpu().numpy()
        return rows[:, 0] > 0.5 if name == "terminated" else rows

    def latest(self, s: int, n: int, name: str = "obs") -> np.ndarray:
        """Field `name` of specialist s's latest min(n, size) rows, oldest first (numpy)."""
        n = min(n, self.size)
        return self.take(s, (self.ptr - n + np.arange(n)) % self.capacity, name)

    def fill(self, data: dict[str, np.ndarray]) -> None:
        """Start every specialist's ring with the rows `data` (the Zarr layout, oldest first; the
        latest `capacity` of them if there are more); the same rows for all S."""
        n = min(len(data["obs"]), self.capacity)
        rows = {k: np.asarray(v)[len(v) - n :] for k, v in data.items()}
        packed = np.zeros((n, self.rows.shape[2]), np.float32)
        for k, c in self.cols.items():
            packed[:, c] = rows[k].reshape(n, -1)
        with torch.no_grad():
            self.rows[:, :n].copy_(torch.from_numpy(packed))
        for k, v in self.host.items():
            v[:, :n] = rows[k]
        self.size, self.ptr = n, n % self.capacity

    def chronological(self, s: int) -> dict[str, np.ndarray]:
        """Specialist s's stored rows, oldest first, as the numpy fields of the Zarr format."""
        if self.size < self.capacity:
            order = np.arange(self.size)
        else:
            order = np.concatenate([np.arange(self.ptr, self.capacity), np.arange(0, self.ptr)])
        rows = self.rows[s].cpu().numpy()[order]
        c = self.cols
        out = {k: np.ascontiguousarray(rows[:, c[k]]) for k in ("obs", "action", "reward", "next_obs")}
        out["terminated"] = rows[:, c["terminated"]][:, 0] > 0.5
        for k, v in self.host.items():
            out[k] = v[s][order]
        return out
