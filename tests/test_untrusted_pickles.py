"""Crafted statistics files and SB3 zips (issue 42's attacks on the restricted unpickler, rebuilt
from its description) end in one line naming the file, in a process that survives, with bounded
memory. Each read runs in a fresh interpreter under an address-space limit, so a crash fails the
test instead of killing pytest.

The files are written with the pickler of benchmarks/fuzz_imports.py (which writes SB3's class
names without SB3); the reads are mapex's own (`read_vecnormalize`, `read_policy`)."""

from __future__ import annotations

import base64
import importlib.util
import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("fuzz_imports", ROOT / "benchmarks" / "fuzz_imports.py")
fuzz = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(fuzz)

HEADROOM_MB = 512  # address space the read may add (RLIMIT_AS); its real needs are a few MB
CHILD = r"""
import json, resource, sys
from pathlib import Path

from pipeline.core.artifacts import ArtifactError
from pipeline.core.envs import EnvSpec
from pipeline.interop.readers import read_policy
from pipeline.interop.vecnorm import read_vecnormalize


def status(key):
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) << 10


headroom = int(sys.argv[1]) << 20
start = status("VmSize")
resource.setrlimit(resource.RLIMIT_AS, (start + headroom, start + headroom))
for fmt, path in zip(sys.argv[2::2], sys.argv[3::2]):
    try:
        if fmt == "stats":
            read_vecnormalize(path)
        else:
            read_policy(path, fmt, EnvSpec("fuzz-v0", 5, 2, 2, (-1.0, -1.0), (1.0, 1.0), 40))
        print(json.dumps({"outcome": "accepted", "vm_growth": status("VmPeak") - start}), flush=True)
    except ArtifactError as exc:
        print(json.dumps({"outcome": "refused", "message": str(exc), "vm_growth": status("VmPeak") - start}), flush=True)
"""


def read_isolated(files: list[tuple[str, Path]]) -> list[dict]:
    """Read each (format or "stats", path) in turn in one fresh interpreter; their outcomes,
    asserting it exited cleanly (a crash on any file fails the test, naming what came before)."""
    env = os.environ | {"PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    args = [str(x) for pair in files for x in pair]
    r = subprocess.run(
        [sys.executable, "-c", CHILD, str(HEADROOM_MB), *args], capture_output=True, text=True, env=env, timeout=300
    )
    assert r.returncode == 0, f"exit {r.returncode} (a negative one is a signal) after {r.stdout}: {r.stderr[-2000:]}"
    lines = r.stdout.strip().splitlines()
    assert len(lines) == len(files), r.stdout
    return [json.loads(line) for line in lines]


def assert_refused(out: dict, path: Path, *says: str) -> str:
    assert out["outcome"] == "refused", out
    message = out["message"]
    assert "\n" not in message and message.startswith(str(path)), message
    for words in says:
        assert words in message, message
    assert out["vm_growth"] < 256 << 20, out  # nothing big was even reserved
    return message


def test_a_void_dtype_given_an_object_field_is_refused_and_the_process_survives(tmp_path):
    """Attack 1: a BUILD on a void dtype adds an object field while its flags stay 0 (numpy then
    takes the file's bytes for pointers: formerly a SIGSEGV on reading norm_obs's repr)."""
    paths = [tmp_path / f"{where}.pkl" for where in ("norm_obs", "obs_rms.mean")]
    for path in paths:
        path.write_bytes(fuzz.void_dtype_with_object_field(path.stem))
    for path, out in zip(paths, read_isolated([("stats", p) for p in paths])):
        assert_refused(out, path, "asks for dtype 'V8'", "only plain numbers")


def test_a_plain_dtype_given_fields_or_flags_by_build_is_refused(tmp_path):
    f8 = fuzz.Call(fuzz.Name("numpy", "dtype"), ("f8", False, True))
    reconstruct = fuzz.Name("numpy._core.multiarray", "_reconstruct")
    paths = []
    for i, state in enumerate(
        (
            (3, "<", None, ("a",), {"a": (f8, 0)}, 8, 1, 0),  # fields on a float
            (3, "<", None, None, None, -1, -1, 63),  # object flags
            (4, "<", None, None, None, -1, -1, 0, {"m": 1}),  # metadata
        )
    ):
        dtype = fuzz._Built(f8, state)
        mean = fuzz._Built(
            fuzz.Call(reconstruct, (fuzz.Name("numpy", "ndarray"), (0,), b"b")), (1, (5,), dtype, False, b"\0" * 40)
        )
        paths.append(tmp_path / f"stats{i}.pkl")
        paths[-1].write_bytes(fuzz.dumps(fuzz.vecnormalize(mean, np.ones(5)), 4))
    for path, out in zip(paths, read_isolated([("stats", p) for p in paths])):
        assert_refused(out, path, "gives dtype f8 a state other than a byte order")


def huge_shape(form: str, nbytes: int) -> bytes:
    """Statistics whose mean declares `nbytes` of data in one of numpy's reduction forms."""
    reconstruct = fuzz.Name("numpy._core.multiarray", "_reconstruct")
    ndarray, f8 = fuzz.Name("numpy", "ndarray"), np.dtype("f8")
    if form == "reconstruct":  # numpy's _reconstruct allocating the shape (int8 placeholder)
        mean = fuzz.Call(reconstruct, (ndarray, (nbytes,), b"b"))
    elif form == "build":  # the BUILD state declares the shape, with 8 bytes of data
        mean = fuzz._Built(fuzz.Call(reconstruct, (ndarray, (0,), b"b")), (1, (nbytes // 8,), f8, False, b"\0" * 8))
    else:  # protocol 5's _frombuffer
        mean = fuzz.Call(fuzz.Name("numpy._core.numeric", "_frombuffer"), (b"\0" * 8, f8, (nbytes // 8,), "C"))
    sb3 = "stable_baselines3.common"  # the least a VecNormalize file holds: a few hundred bytes
    rms = fuzz.Obj(fuzz.Name(f"{sb3}.running_mean_std", "RunningMeanStd"), {"mean": mean, "var": np.ones(5)})
    stats = fuzz.Obj(fuzz.Name(f"{sb3}.vec_env.vec_normalize", "VecNormalize"), {"obs_rms": rms, "norm_obs": True})
    return fuzz.dumps(stats, 4)


def test_a_tiny_file_declaring_a_huge_shape_is_refused_before_allocating(tmp_path):
    """Attack 3: a file of a few hundred bytes declaring 1.75 GB (and one declaring 2**62 bytes),
    in each of numpy's three ways of rebuilding an array."""
    files, expect = [], []
    for form in ("reconstruct", "build", "frombuffer"):
        for nbytes in (1_750_000_000, 2**62):
            path = tmp_path / f"{form}{nbytes}.pkl"
            path.write_bytes(huge_shape(form, nbytes))
            assert path.stat().st_size < 500
            dim = nbytes if form == "reconstruct" else nbytes // 8
            says = "refused before allocating" if form == "reconstruct" else "8 bytes of data"
            files.append(("stats", path))
            expect.append((str(dim), says if dim < 1 << 31 else "declares an array dimension of"))
    for (_, path), out, says in zip(files, read_isolated(files), expect):
        assert_refused(out, path, *says)


def sb3_zip(tmp_path: Path, last_obs: bytes | None = None, edit=None, policy: bytes | None = None) -> Path:
    """The fuzz benchmark's SB3 model.zip (written without SB3), its `_last_obs` replaced by
    `last_obs`, its `data` changed by `edit(doc)`, its `policy.pth` replaced by `policy`."""
    seed = fuzz.build_seeds(tmp_path / "seeds", ("sb3",))["sb3"]
    out = tmp_path / "model.zip"
    with zipfile.ZipFile(seed) as src, zipfile.ZipFile(out, "w") as dst:
        for name in src.namelist():
            body = src.read(name)
            if name == "data":
                doc = json.loads(body)
                if last_obs is not None:
                    doc["_last_obs"][":serialized:"] = base64.b64encode(last_obs).decode()
                if edit is not None:
                    edit(doc)
                body = json.dumps(doc).encode()
            if name == "policy.pth" and policy is not None:
                body = policy
            dst.writestr(name, body)
    return out


def test_an_sb3_zip_whose_last_obs_carries_the_attacks_is_refused(tmp_path):
    """Every SB3 import unpickles `_last_obs` through the same reader: the same attacks, and one
    that would run code, end in one line naming the zip and the entry; the valid zip is accepted."""
    valid = sb3_zip(
        tmp_path,
        base64.b64decode(
            json.loads(zipfile.ZipFile(fuzz.build_seeds(tmp_path / "plain", ("sb3",))["sb3"]).read("data"))[
                "_last_obs"
            ][":serialized:"]
        ),
    )
    files = [("sb3", valid)]
    reconstruct = fuzz.Name("numpy._core.multiarray", "_reconstruct")
    void = fuzz._Built(
        fuzz.Call(fuzz.Name("numpy", "dtype"), ("V8", False, True)),
        (3, "|", None, ("a",), {"a": (np.dtype("O"), 0)}, 8, 1, 0),
    )
    marker = tmp_path / "code_ran"
    attacks = {
        "asks for dtype 'V8'": fuzz.dumps(
            fuzz._Built(
                fuzz.Call(reconstruct, (fuzz.Name("numpy", "ndarray"), (0,), b"b")), (1, (1, 5), void, False, b"A" * 40)
            ),
            4,
        ),
        "refused before allocating": fuzz.dumps(
            fuzz.Call(reconstruct, (fuzz.Name("numpy", "ndarray"), (1_750_000_000,), b"b")), 4
        ),
        "refers to posix.system": fuzz.code_payloads(marker)[1],
    }
    for i, blob in enumerate(attacks.values()):
        (tmp_path / str(i)).mkdir()
        files.append(("sb3", sb3_zip(tmp_path / str(i), blob)))
    outs = read_isolated(files)
    assert outs[0]["outcome"] == "accepted", outs[0]
    for (_, path), out, says in zip(files[1:], outs[1:], attacks):
        assert_refused(out, path, "data['_last_obs']", says)
    assert not marker.exists()


def test_an_sb3_zip_with_crafted_sizes_or_code_in_its_settings_is_refused(tmp_path):
    """Tensors saved as expanded views (16384 x 16384 floats from one stored zero: building the
    actor would allocate 1 GB), a space of 2**40 dims, and policy_kwargs naming builtins.exec."""
    import torch

    n = 1 << 14
    one = torch.zeros(1)
    policy = {
        "actor.mu.0.weight": one.expand(n, 5),
        "actor.mu.0.bias": one.expand(n),
        "actor.mu.2.weight": one.expand(n, n),
        "actor.mu.2.bias": one.expand(n),
        "actor.mu.4.weight": one.expand(2, n),
        "actor.mu.4.bias": torch.zeros(2),
    }
    expanded = fuzz.torch_bytes(policy)
    assert len(expanded) < 10_000

    def huge_space(doc):
        doc["action_space"]["_shape"] = [2**40]

    def exec_kwargs(doc):
        payload = fuzz.dumps({"net_arch": fuzz.Call(fuzz.Name("builtins", "exec"), ("print(1)",))}, 4)
        doc["policy_kwargs"][":serialized:"] = base64.b64encode(payload).decode()

    cases = {
        "declares tensors of": dict(policy=expanded),
        "action space is <class 'gymnasium.spaces.box.Box'> of shape [1099511627776]": dict(edit=huge_space),
        "policy_kwargs refer to code (builtins.exec)": dict(edit=exec_kwargs),
    }
    files = []
    for i, kwargs in enumerate(cases.values()):
        (tmp_path / str(i)).mkdir()
        files.append(("sb3", sb3_zip(tmp_path / str(i), **kwargs)))
    for (_, path), out, says in zip(files, read_isolated(files), cases):
        assert_refused(out, path, says)


def test_a_torchscript_archive_whose_tensors_outgrow_their_records_is_refused_before_loading(tmp_path):
    """torch.jit.load trusts data.pkl for each storage's size: a record emptied while data.pkl
    still declares its elements crashed it (SIGSEGV, found by the fuzz benchmark). Checked first:
    an emptied record, a weight whose shape reaches past its storage; the valid file is accepted."""
    seed = fuzz.build_seeds(tmp_path / "seeds", ("torchscript",))["torchscript"].read_bytes()
    members = fuzz.zip_members(seed)
    root = members[0][0].split("/")[0]
    emptied = [(n, b"" if n == f"{root}/data/3" else b) for n, b in members]
    weight = b"K\x08K\x05t(K\x05K\x01t"  # net.0.weight: sizes (8, 5), strides (5, 1)
    data_pkl = dict(members)[f"{root}/data.pkl"]
    assert data_pkl.count(weight) == 1
    grown = [(n, b.replace(weight, b"K\tK\x05t(K\x05K\x01t") if n.endswith("data.pkl") else b) for n, b in members]
    files = [("torchscript", tmp_path / "valid.ts")]
    files[0][1].write_bytes(seed)
    for name, archive in (("emptied.ts", emptied), ("grown.ts", grown)):
        (tmp_path / name).write_bytes(fuzz.zip_bytes(archive))
        files.append(("torchscript", tmp_path / name))
    valid, emptied_out, grown_out = read_isolated(files)
    assert valid["outcome"] == "accepted", valid
    assert_refused(emptied_out, files[1][1], "declares 8 bytes for storage '3'", "its record has 0 bytes")
    assert_refused(grown_out, files[2][1], "reaching past the 40 elements of its storage")
