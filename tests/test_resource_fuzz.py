"""Hostile files that cost memory or time, not code (issue 57): each read in a subprocess under a
CPU-time limit, asserting a one-line refusal naming the file (or a correct load) and memory growth
(the child's peak RSS after its imports to its end) within the budget of docs/trust.md.

Classes: an SB3 entry of millions of pickle opcodes (listing them built ~900 MiB), a Zarr buffer
declaring a huge shape over no chunk files (1 GiB allocated before the shape check) or a pickle
codec, a TorchScript member declaring (and inflating to) more than the cap, a TorchScript data.pkl
of integer keys that all hash alike (quadratic inserts), and the valid files of each, mutated
nowhere, which must still load."""

from __future__ import annotations

import base64
import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
BUDGET_MB = 160  # memory growth allowed beyond the reader's imports (the files here are under 3 MB)
CPU_S = 20  # RLIMIT_CPU of each child

CHILD = r"""
import json, resource, sys, time
resource.setrlimit(resource.RLIMIT_CPU, ({cpu}, {cpu}))
kind, path = sys.argv[1], sys.argv[2]
from pipeline.core.artifacts import ArtifactError
from pipeline.core.buffer import load_buffer
from pipeline.core.tscheck import check_torchscript
from pipeline.interop.readers import read_sb3
from pipeline.interop.vecnorm import read_vecnormalize
import torch  # noqa: F401  (its own arenas counted before the read)
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
t0 = time.process_time()
try:
    if kind == "sb3":
        read_sb3(__import__("pathlib").Path(path))
    elif kind == "zarr":
        load_buffer(path)
    elif kind == "stats":
        read_vecnormalize(path)
    elif kind == "cleanrl":  # a CleanRL checkpoint's load (the torch.save zip every torch-file import reads)
        from pipeline.interop.readers import _weights_only
        _weights_only(__import__("pathlib").Path(path), None, "the checkpoint")
    else:
        check_torchscript(open(path, "rb").read(), path)
    out = {{"ok": True}}
except ArtifactError as exc:
    out = {{"ok": False, "error": str(exc)}}
out["grow_mb"] = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
out["base_mb"] = before / 1024
out["cpu_s"] = time.process_time() - t0
print(json.dumps(out))
"""


def read_limited(kind: str, path: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run(
        [sys.executable, "-c", CHILD.format(cpu=CPU_S), kind, str(path)],
        capture_output=True,
        text=True,
        env=env,
        cwd=ROOT,
        timeout=120,
    )
    assert r.returncode == 0, f"{kind} {path}: the reader died (rc {r.returncode}):\n{r.stderr[-2000:]}"
    assert "Traceback" not in r.stderr, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    if log := os.environ.get("MAPEX_FUZZ_LOG"):  # benchmarks/bench_trust.py collects the figures
        with open(log, "a") as f:
            f.write(json.dumps({"kind": kind, "case": path.name, "bytes": _size(path)} | out) + "\n")
    return out


def _size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) if path.is_dir() else path.stat().st_size


def assert_refused(out: dict, path: Path, says: str) -> None:
    assert not out["ok"], f"{path}: accepted"
    line = out["error"]
    assert "\n" not in line and str(path) in line and says in line, line
    assert out["grow_mb"] < BUDGET_MB, f"{path}: grew {out['grow_mb']:.0f} MB ({line})"
    assert out["cpu_s"] < CPU_S / 2, f"{path}: {out['cpu_s']:.1f} s of CPU ({line})"


# ------------------------------------------------------------------------------------- Zarr


def _buffer(path: Path) -> Path:
    from pipeline.core.buffer import ReplayBuffer, save_buffer

    rng = np.random.default_rng(0)
    b = ReplayBuffer(500, 3, 2, 2)
    for i in range(300):
        b.add(
            rng.normal(size=3),
            rng.normal(size=2),
            rng.normal(size=2),
            rng.normal(size=3),
            False,
            i % 50 == 49,
            i // 50,
            i % 50,
        )
    attrs = {"obs_dim": 3, "act_dim": 2, "n_objectives": 2, "env_id": "x", "objective": 0, "seed": 0}
    save_buffer(path, b.chronological(), {**attrs, "max_episode_steps": 50})
    return path


def _edit_json(file: Path, edit) -> None:
    doc = json.loads(file.read_text())
    edit(doc)
    file.write_text(json.dumps(doc))


def test_zarr_buffers_that_declare_what_they_do_not_hold_are_refused_before_allocating(tmp_path):
    valid = _buffer(tmp_path / "valid.zarr")
    out = read_limited("zarr", valid)
    assert out["ok"], out

    rows = 90_000_000  # 90M rows x (3+3+2+2) float32 = 3.6 GB declared, over ~2 KB of metadata
    huge = _buffer(tmp_path / "huge.zarr")
    for name in ("obs", "action", "reward", "next_obs", "terminated", "truncated", "episode", "episode_step"):
        meta = huge / name / "zarr.json"
        _edit_json(meta, lambda d: d.__setitem__("shape", [rows, *d["shape"][1:]]))
        for chunk in (huge / name / "c").rglob("*") if (huge / name / "c").exists() else []:
            if chunk.is_file():
                chunk.unlink()
    _edit_json(huge / "zarr.json", lambda d: d["attributes"].__setitem__("n_transitions", rows))
    assert_refused(read_limited("zarr", huge), huge, "declare")

    codec = _buffer(tmp_path / "codec.zarr")
    _edit_json(codec / "obs" / "zarr.json", lambda d: d.__setitem__("codecs", [{"name": "pickle"}]))
    assert_refused(read_limited("zarr", codec), codec, "codecs")

    dtype = _buffer(tmp_path / "dtype.zarr")
    _edit_json(dtype / "reward" / "zarr.json", lambda d: d.__setitem__("data_type", "float64"))
    assert_refused(read_limited("zarr", dtype), dtype, "data_type")

    shape = _buffer(tmp_path / "shape.zarr")
    _edit_json(shape / "action" / "zarr.json", lambda d: d.__setitem__("shape", [300, 7]))
    assert_refused(read_limited("zarr", shape), shape, "expected (T, 2)")


# -------------------------------------------------------------------------------- TorchScript


def _torchscript(path: Path) -> Path:
    import torch

    torch.jit.script(torch.nn.Linear(3, 2)).save(str(path))
    return path


def _rewritten(src: Path, dst: Path, replace: dict[str, bytes], compress: int = zipfile.ZIP_STORED) -> Path:
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w") as zout:
        for info in zin.infolist():
            body = zin.read(info.filename)
            for suffix, new in replace.items():
                if info.filename.endswith(suffix):
                    body = new
            zout.writestr(info.filename, body, compress_type=compress)
    return dst


def test_torchscript_members_that_inflate_or_flood_are_refused_in_bounded_memory_and_time(tmp_path):
    valid = _torchscript(tmp_path / "valid.pt")
    assert read_limited("ts", valid)["ok"]

    # a data.pkl declaring (and inflating to) 64 MB from a few KB of deflated zeros
    inflating = _rewritten(valid, tmp_path / "inflate.pt", {"/data.pkl": b"\x00" * (64 << 20)}, zipfile.ZIP_DEFLATED)
    assert inflating.stat().st_size < 1 << 20
    assert_refused(read_limited("ts", inflating), inflating, "refused above")

    # 60,000 integer keys that all hash to 0 (k * (2**61 - 1)): quadratic inserts into a real dict
    modulus = (1 << 61) - 1
    body = bytearray(b"\x80\x02}(")  # PROTO 2, EMPTY_DICT, MARK
    for k in range(1, 60_001):
        key = (k * modulus).to_bytes(12, "little", signed=True)
        body += b"\x8a" + bytes([len(key)]) + key + b"N"  # LONG1 key, NONE
    body += b"u."  # SETITEMS, STOP
    flood = _rewritten(valid, tmp_path / "flood.pt", {"/data.pkl": bytes(body)})
    out = read_limited("ts", flood)
    assert out["cpu_s"] < 3, f"{flood}: {out['cpu_s']:.1f} s of CPU reading 60,000 colliding keys"
    assert out["grow_mb"] < BUDGET_MB


# ------------------------------------------------------------------------------------------ SB3


def test_an_sb3_entry_of_millions_of_opcodes_is_refused_without_listing_them(tmp_path):
    from test_untrusted_pickles import sb3_zip

    valid = sb3_zip(tmp_path / "v")
    assert read_limited("sb3", valid)["ok"]
    (tmp_path / "h").mkdir()
    flood = base64.b64encode(b"\x80\x04" + b"(" * 3_000_000 + b".").decode()  # 3M MARK opcodes, 3 MB
    hostile = sb3_zip(tmp_path / "h", edit=lambda doc: doc.__setitem__("policy_class", {":serialized:": flood}))
    assert_refused(read_limited("sb3", hostile), hostile, "opcodes")


# ---------------------------------------------------------------- paths in params (item 4)


def test_import_paths_outside_the_repository_are_refused_unless_the_user_says_so(tmp_path, monkeypatch):
    import pydantic

    from pipeline.params.import_specialists import ALLOW_OUTSIDE, ImportedPolicyEntry

    repo = tmp_path / "repo"
    (repo / "models").mkdir(parents=True)
    (tmp_path / "elsewhere").mkdir()
    (repo / "models" / "link").symlink_to(tmp_path / "elsewhere")
    monkeypatch.chdir(repo)
    monkeypatch.delenv(ALLOW_OUTSIDE, raising=False)
    assert ImportedPolicyEntry(objective=0, file="models/a.zip", format="sb3").file == "models/a.zip"
    assert ImportedPolicyEntry(objective=0, file=str(repo / "models/a.zip"), format="sb3")
    outside = [
        {"file": "/etc/passwd"},
        {"file": "../elsewhere/a.zip"},
        {"file": "models/link/a.zip"},  # a link inside that leads out
        {"file": "models/a.zip", "buffer": "~/buffer.zarr"},
        {"file": "models/a.zip", "normalize": "models/../../elsewhere/vecnormalize.pkl"},
    ]
    for entry in outside:
        with pytest.raises(pydantic.ValidationError) as err:
            ImportedPolicyEntry(objective=0, format="sb3", **entry)
        text = str(err.value)
        assert "outside the repository" in text and f"{ALLOW_OUTSIDE}=1" in text, entry
    monkeypatch.setenv(ALLOW_OUTSIDE, "1")
    for entry in outside:
        ImportedPolicyEntry(objective=0, format="sb3", **entry)


# ------------------------------------------------------------------------- statistics files


def test_a_statistics_file_of_colliding_keys_is_refused_before_any_insert(tmp_path):
    """40,000 integer keys that all hash alike (80,000 opcodes: under the opcode cap, about 9 s of
    quadratic inserts before), by SETITEMS and by the older DICT opcode: refused at the first
    non-str key (a real VecNormalize file has only str keys), in well under a second."""
    modulus = (1 << 61) - 1
    keys = bytearray()
    for k in range(1, 40_001):
        key = (k * modulus).to_bytes(12, "little", signed=True)
        keys += b"\x8a" + bytes([len(key)]) + key + b"N"  # LONG1 key, NONE
    for name, body in (
        ("setitems.pkl", b"\x80\x02}(" + bytes(keys) + b"u."),  # EMPTY_DICT, MARK, ..., SETITEMS
        ("dict.pkl", b"\x80\x02(" + bytes(keys) + b"d."),  # MARK, ..., DICT
    ):
        path = tmp_path / name
        path.write_bytes(body)
        out = read_limited("stats", path)
        assert_refused(out, path, "str keys")
        assert out["cpu_s"] < 1, f"{path}: {out['cpu_s']:.1f} s of CPU"


# ------------------------------------------------------------------ CleanRL (torch.save zips)


def test_a_cleanrl_checkpoint_that_inflates_or_floods_is_refused_before_torch_load(tmp_path):
    import torch

    valid = tmp_path / "valid.cleanrl_model"
    torch.save((torch.nn.Linear(3, 4).state_dict(), torch.nn.Linear(2, 1).state_dict()), valid)
    assert read_limited("cleanrl", valid)["ok"]

    inflating = _rewritten(
        valid, tmp_path / "inflate.cleanrl_model", {"/data.pkl": b"\x00" * (64 << 20)}, zipfile.ZIP_DEFLATED
    )
    assert inflating.stat().st_size < 1 << 20
    assert_refused(read_limited("cleanrl", inflating), inflating, "refused above")

    # 40,000 colliding integer keys: torch.load's own unpickler would insert them all (quadratic)
    modulus = (1 << 61) - 1
    body = bytearray(b"\x80\x02}(")
    for k in range(1, 40_001):
        key = (k * modulus).to_bytes(12, "little", signed=True)
        body += b"\x8a" + bytes([len(key)]) + key + b"N"
    body += b"u."
    flood = _rewritten(valid, tmp_path / "flood.cleanrl_model", {"/data.pkl": bytes(body)})
    out = read_limited("cleanrl", flood)
    assert out["cpu_s"] < 3, f"{flood}: {out['cpu_s']:.1f} s of CPU"
    assert out["grow_mb"] < BUDGET_MB
