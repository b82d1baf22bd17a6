"""Fuzz the imports: mutated model and statistics files, each read in a child process with a
memory limit and a timeout; counts clean refusals, accepted files, crashes, hangs, files that ran
code, and peak memory (docs/benchmarks.md, "Fuzzing the imports").

Seeds are small valid files this script builds itself (no SB3, CleanRL or rl-zoo3 needed): an SB3
`model.zip` (its `data` JSON, `policy.pth`, `critic.optimizer.pth`, `_last_obs` pickled as
cloudpickle does), a CleanRL checkpoint, a TorchScript actor, a torch.export program (.pt2) and
an SB3 VecNormalize statistics file. Each case is one seed mutated one way:

- flip: 1 to 16 bytes set to random values, in the file or (in half the zips) inside one member,
  the zip rewritten around it so that its CRC holds;
- truncate: the file cut at a random length;
- pickle_ops: one opcode of a pickle inside the file deleted, swapped with another, duplicated,
  or an opcode inserted (MARK, BUILD, REDUCE, memo indices of 2**31, byte strings that declare
  gigabytes, ...): the statistics file itself, the SB3 `_last_obs` entry, the `data.pkl` of a
  torch file;
- oversize: an integer in a pickle (an array's shape, a tensor's size) or a JSON (an SB3 space's
  shape, a .pt2 tensor's sizes) replaced by a huge or negative one, or an array declared with a
  huge shape in a tiny statistics file;
- zip: a member of a zip (SB3, torch files) renamed, removed, duplicated or emptied;
- code: a file that would run code when loaded (a pickle naming os.system, posix.system or
  builtins.exec that writes a marker file, placed where each format unpickles: the statistics,
  `_last_obs`, `policy_kwargs`, `policy.pth`, a torch file's `data.pkl`, a TorchScript's
  constants, a .pt2's weights or constants marked `use_pickle`, its legacy weights file, its
  sample inputs); a case whose marker appears counts as "code ran";
- seed: the seed itself, unmutated (it must be accepted).

Each case is read by `pipeline.interop.readers.read_policy` (the four model formats, for a 5-d
observation, 2-d action env spec) or `pipeline.interop.vecnorm.read_vecnormalize` in a child
forked from a server process that has imported torch and the readers once (and read every seed,
so lazy imports are done): the child's address space may grow by at most --memory-mb over the
server's (RLIMIT_AS), and it is killed after --timeout seconds. Outcomes: "refused" (an
ArtifactError of one line naming the file), "accepted", "crash" (a signal, a non-zero exit, an
uncaught exception, or a refusal of several lines), "hang" (killed at the timeout); "code ran"
is counted on top. Peak memory is the children's ru_maxrss (which includes the pages shared
with the server) and its growth over the server's resident size.

    python benchmarks/fuzz_imports.py --cases 2000 --out fuzz_imports.json
"""

from __future__ import annotations

import argparse
import base64
import io
import json
import os
import pickle
import random
import resource
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
import warnings
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

FORMATS = ("sb3", "cleanrl", "torchscript", "torch_export", "stats")
KINDS = ("flip", "truncate", "pickle_ops", "oversize", "zip", "code", "seed")
OBS, ACT, HIDDEN = 5, 2, 8
SEED_FILES = {
    "sb3": "model.zip",
    "cleanrl": "actor.cleanrl_model",
    "torchscript": "actor.ts",
    "torch_export": "actor.pt2",
    "stats": "vecnormalize.pkl",
}
HUGE = (2**31 - 1, 2**32, 2**40, 2**62, 2**63 - 1, 2**64 + 5, -1, -(2**31), 10**30)


# -- pickles of SB3 objects, written without SB3 --------------------------------------------------


class Name:
    """A global `module.name` as a pickle refers to it (the class or function need not exist here)."""

    def __init__(self, module: str, name: str):
        self.module, self.name = module, name


class Obj:
    """An instance of class `cls` (a Name) with `state`, pickled as NEWOBJ then BUILD."""

    def __init__(self, cls: Name, state: Any):
        self.cls, self.state = cls, state


class Call:
    """A call of `func` (a Name) with `args` when unpickled: REDUCE."""

    def __init__(self, func: Name, args: tuple):
        self.func, self.args = func, args


class _Pickler(pickle._Pickler):  # the pure-Python pickler: its `save` can write a Name as a global
    def save(self, obj: Any, save_persistent_id: bool = True) -> None:
        if isinstance(obj, Name):
            if self.proto >= 4:
                self.save(obj.module)
                self.save(obj.name)
                self.write(pickle.STACK_GLOBAL)
            else:
                self.write(pickle.GLOBAL + f"{obj.module}\n{obj.name}\n".encode())
            return
        super().save(obj, save_persistent_id)

    def reducer_override(self, obj: Any) -> Any:
        if isinstance(obj, Obj):
            return (Name("copyreg", "__newobj__"), (obj.cls,), obj.state)
        if isinstance(obj, Call):
            return (obj.func, obj.args)
        return NotImplemented

    def save_reduce(self, func, args, state=None, *rest, obj=None):  # noqa: ANN001 (pickle's signature)
        if not isinstance(func, Name):
            return super().save_reduce(func, args, state, *rest, obj=obj)
        if func.name == "__newobj__":  # NEWOBJ of a class that is only a Name
            self.save(args[0])
            self.save(args[1:])
            self.write(pickle.NEWOBJ)
        else:
            self.save(func)
            self.save(args)
            self.write(pickle.REDUCE)
        if state is not None:
            self.save(state)
            self.write(pickle.BUILD)


def dumps(obj: Any, protocol: int = 4) -> bytes:
    buf = io.BytesIO()
    _Pickler(buf, protocol).dump(obj)
    return buf.getvalue()


SB3 = "stable_baselines3.common"
BOX = Name("gymnasium.spaces.box", "Box")


def box_state(n: int, bound: float) -> dict:
    low = np.full(n, -bound, np.float32)
    return {
        "dtype": np.dtype("float32"),
        "_shape": (n,),
        "low": low,
        "high": -low,
        "bounded_below": np.isfinite(low),
        "bounded_above": np.isfinite(low),
        "_np_random": None,
    }


def vecnormalize(mean: Any, var: Any) -> Obj:
    rms = Name(f"{SB3}.running_mean_std", "RunningMeanStd")
    return Obj(
        Name(f"{SB3}.vec_env.vec_normalize", "VecNormalize"),
        {
            "obs_rms": Obj(rms, {"mean": mean, "var": var, "count": 1000.0001}),
            "ret_rms": Obj(rms, {"mean": np.float64(0.5), "var": np.float64(2.0), "count": 1000.0001}),
            "clip_obs": 10.0,
            "clip_reward": 10.0,
            "norm_obs": True,
            "norm_reward": True,
            "training": True,
            "gamma": 0.99,
            "epsilon": 1e-8,
            "num_envs": 1,
            "observation_space": Obj(BOX, box_state(OBS, np.inf)),
            "action_space": Obj(BOX, box_state(ACT, 1.0)),
        },
    )


# -- seeds ----------------------------------------------------------------------------------------


def mlp_state(prefix: str, sizes: list[int], gen) -> dict:
    import torch

    out, names = {}, [f"{prefix}{2 * i}" for i in range(len(sizes) - 1)]
    for name, (a, b) in zip(names, zip(sizes[:-1], sizes[1:])):
        out[f"{name}.weight"] = torch.randn(b, a, generator=gen) * 0.3
        out[f"{name}.bias"] = torch.randn(b, generator=gen) * 0.1
    return out


def torch_bytes(obj: Any) -> bytes:
    import torch

    buf = io.BytesIO()
    torch.save(obj, buf)
    return buf.getvalue()


def serialized(obj: Any) -> str:
    return base64.b64encode(obj if isinstance(obj, bytes) else dumps(obj, 5)).decode()


def sb3_data(last_obs: str, last_original: str) -> dict:
    def space(n: int, bound: str) -> dict:
        return {
            ":type:": "<class 'gymnasium.spaces.box.Box'>",
            ":serialized:": serialized(Obj(BOX, box_state(n, 1.0))),
            "dtype": "float32",
            "_shape": [n],
            "low": "[" + " ".join([f"-{bound}"] * n) + "]",
            "high": "[" + " ".join([bound] * n) + "]",
            "bounded_below": "[" + " ".join(["True"] * n) + "]",
            "_np_random": None,
        }

    return {
        "policy_class": {
            ":type:": "<class 'abc.ABCMeta'>",
            ":serialized:": serialized(Name("stable_baselines3.td3.policies", "TD3Policy")),
            "__module__": "stable_baselines3.td3.policies",
        },
        "observation_space": space(OBS, "inf"),
        "action_space": space(ACT, "1."),
        "policy_kwargs": {":type:": "<class 'dict'>", ":serialized:": serialized({"net_arch": [HIDDEN, HIDDEN]})},
        "use_sde": False,
        "_last_obs": {":type:": "<class 'numpy.ndarray'>", ":serialized:": last_obs},
        "_last_original_obs": {":type:": "<class 'numpy.ndarray'>", ":serialized:": last_original},
        "num_timesteps": 200,
        "gamma": 0.99,
    }


def write_zip(path: Path, members: list[tuple[str, bytes]]) -> None:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as zf:
        for name, data in members:
            zf.writestr(name, data)


def build_seeds(folder: Path, formats: tuple[str, ...] = FORMATS) -> dict[str, Path]:
    """Valid seed files of `formats` (all five by default) in `folder`, by format."""
    import torch
    from torch import nn

    gen = torch.Generator().manual_seed(0)
    folder.mkdir(parents=True, exist_ok=True)
    paths = {fmt: folder / name for fmt, name in SEED_FILES.items()}
    rng = np.random.default_rng(0)

    # SB3 TD3: actor.mu = Linear ReLU Linear ReLU Linear; the critic's Adam state for input scales
    policy = mlp_state("actor.mu.", [OBS, HIDDEN, HIDDEN, ACT], gen) | mlp_state(
        "critic.qf0.", [OBS + ACT, HIDDEN, 1], gen
    )
    optimizer = {
        "state": {0: {"step": torch.tensor(100.0), "exp_avg": torch.zeros(HIDDEN, OBS + ACT)}},
        "param_groups": [{"lr": 1e-3, "params": [0]}],
    }
    optimizer["state"][0]["exp_avg_sq"] = torch.rand(HIDDEN, OBS + ACT, generator=gen) * 1e-4
    mean, std = rng.normal(size=OBS), rng.uniform(0.5, 2.0, size=OBS)
    raw = rng.normal(size=(1, OBS)).astype(np.float32)
    seen = np.clip((raw - mean) / np.sqrt(std**2 + 1e-8), -10, 10).astype(np.float32)
    data = sb3_data(serialized(pickle.dumps(seen, protocol=5)), serialized(pickle.dumps(raw, protocol=5)))
    write_zip(
        paths["sb3"],
        [
            ("data", json.dumps(data).encode()),
            ("policy.optimizer.pth", torch_bytes({"state": {}, "param_groups": []})),
            ("critic.optimizer.pth", torch_bytes(optimizer)),
            ("actor.optimizer.pth", torch_bytes({"state": {}, "param_groups": []})),
            ("policy.pth", torch_bytes(policy)),
            ("pytorch_variables.pth", torch_bytes({})),
            ("_stable_baselines3_version", b"2.7.0"),
            ("system_info.txt", b"- OS: fuzz\n"),
        ],
    )
    paths["stats"].write_bytes(dumps(vecnormalize(mean, std**2), 4))

    # CleanRL TD3: (actor, qf1, qf2) state dicts
    actor = {
        k.replace("actor.mu.0", "fc1").replace("actor.mu.2", "fc2").replace("actor.mu.4", "fc_mu"): v
        for k, v in mlp_state("actor.mu.", [OBS, HIDDEN, HIDDEN, ACT], gen).items()
    }
    actor |= {"action_scale": torch.ones(ACT), "action_bias": torch.zeros(ACT)}
    torch.save((actor, mlp_state("", [OBS + ACT, HIDDEN, 1], gen)), paths["cleanrl"])
    if "torchscript" not in formats and "torch_export" not in formats:
        return {fmt: paths[fmt] for fmt in formats}

    class Policy(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.net = nn.Sequential(nn.Linear(OBS, HIDDEN), nn.ReLU(), nn.Linear(HIDDEN, ACT))

        def forward(self, obs: torch.Tensor) -> torch.Tensor:
            return torch.tanh(self.net(obs))

    torch.manual_seed(0)
    module = Policy().eval()
    torch.jit.save(torch.jit.script(module), paths["torchscript"])
    if "torch_export" in formats:
        batch = {0: torch.export.Dim("batch")}
        program = torch.export.export(module, (torch.zeros(2, OBS),), dynamic_shapes=(batch,))
        torch.export.save(program, paths["torch_export"])
    return {fmt: paths[fmt] for fmt in formats}


# -- mutations ------------------------------------------------------------------------------------


def zip_members(data: bytes) -> list[tuple[str, bytes]]:
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        return [(info.filename, zf.read(info)) for info in zf.infolist()]


def zip_bytes(members: list[tuple[str, bytes]]) -> bytes:
    buf = io.BytesIO()
    with warnings.catch_warnings(), zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        warnings.filterwarnings("ignore", "Duplicate name", UserWarning)  # a duplicate is the point
        for name, data in members:
            zf.writestr(name, data)
    return buf.getvalue()


def replace_member(data: bytes, pick, change) -> bytes:
    """`data` (a zip) with the first member whose name `pick` accepts replaced by `change(bytes)`."""
    members = zip_members(data)
    for i, (name, body) in enumerate(members):
        if pick(name):
            members[i] = (name, change(body))
            return zip_bytes(members)
    raise LookupError("no such member")


def flip(rng: random.Random, data: bytes) -> bytes:
    out = bytearray(data)
    for _ in range(rng.randint(1, 16)):
        i = rng.randrange(len(out))
        out[i] = rng.randrange(256) if rng.random() < 0.5 else out[i] ^ (1 << rng.randrange(8))
    return bytes(out)


def opcode_starts(blob: bytes) -> list[int]:
    import pickletools

    try:
        return [pos for _, _, pos in pickletools.genops(blob)]
    except Exception:  # a pickle already damaged: any byte may start an opcode
        return list(range(len(blob)))


def inserted_opcode(rng: random.Random) -> bytes:
    big = rng.choice((2**31 - 1, 2**32 - 1, 1 << 30))
    return rng.choice(
        (
            pickle.MARK,
            pickle.DUP,
            pickle.POP,
            pickle.BUILD,
            pickle.REDUCE,
            pickle.NEWOBJ,
            pickle.TUPLE,
            pickle.STACK_GLOBAL,
            pickle.EMPTY_DICT + pickle.SETITEMS,
            pickle.APPENDS,
            pickle.LONG_BINPUT + struct.pack("<I", big),
            pickle.LONG_BINGET + struct.pack("<I", big),
            pickle.BINBYTES8 + struct.pack("<Q", 1 << 40),
            pickle.BYTEARRAY8 + struct.pack("<Q", 1 << 62),
            pickle.FRAME + struct.pack("<Q", 1 << 50),
            pickle.LONG4 + struct.pack("<i", 2**31 - 1),
            pickle.BINUNICODE + struct.pack("<I", 2**32 - 1),
            pickle.GLOBAL + b"numpy\ndtype\n",
            pickle.SHORT_BINUNICODE + b"\x02V8",
            pickle.EMPTY_LIST + pickle.MARK + pickle.NONE + pickle.APPENDS,
            pickle.PERSID + b"0\n",
            pickle.NEXT_BUFFER,
            pickle.EXT4 + struct.pack("<I", 0xFFFFFF),
        )
    )


def pickle_op(rng: random.Random, blob: bytes) -> bytes:
    starts = opcode_starts(blob) + [len(blob)]
    if len(starts) < 3:
        return blob + inserted_opcode(rng)
    i = rng.randrange(len(starts) - 1)
    a, b = starts[i], starts[i + 1]
    move = rng.randrange(4)
    if move == 0:  # delete
        return blob[:a] + blob[b:]
    if move == 1:  # duplicate
        return blob[:b] + blob[a:b] + blob[b:]
    if move == 2:  # swap with the next opcode
        if i + 2 >= len(starts):
            return blob[:a] + blob[b:]
        c = starts[i + 2]
        return blob[:a] + blob[b:c] + blob[a:b] + blob[c:]
    return blob[:a] + inserted_opcode(rng) + blob[a:]


def int_opcodes(blob: bytes) -> list[tuple[int, int]]:
    """(start, end) of each integer-literal opcode of a pickle."""
    import pickletools

    out, ops = [], []
    try:
        ops = list(pickletools.genops(blob))
    except Exception:
        return out
    ends = [pos for _, _, pos in ops[1:]] + [len(blob)]
    for (op, _, pos), end in zip(ops, ends):
        if op.name in ("BININT", "BININT1", "BININT2", "LONG1", "INT"):
            out.append((pos, end))
    return out


def encode_int(value: int) -> bytes:
    if -(2**31) <= value < 2**31:
        return pickle.BININT + struct.pack("<i", value)
    raw = value.to_bytes((value.bit_length() + 8) // 8, "little", signed=True)
    return pickle.LONG1 + bytes([len(raw)]) + raw


def oversize_pickle(rng: random.Random, blob: bytes) -> bytes:
    spans = int_opcodes(blob)
    if not spans:
        return pickle_op(rng, blob)
    for _ in range(rng.randint(1, 3)):
        a, b = rng.choice(spans)
        blob = blob[:a] + encode_int(rng.choice(HUGE)) + blob[b:]
        spans = int_opcodes(blob)
        if not spans:
            break
    return blob


def oversize_json(rng: random.Random, text: bytes) -> bytes:
    """A JSON document with 1 to 3 of its integers replaced by huge or negative ones."""
    import re

    spans = [m.span() for m in re.finditer(rb"(?<![\w.\-])\d+(?![\w.])", text)]
    if not spans:
        return text
    for a, b in sorted(rng.sample(spans, min(len(spans), rng.randint(1, 3))), reverse=True):
        text = text[:a] + str(rng.choice(HUGE)).encode() + text[b:]
    return text


def huge_shape_stats(rng: random.Random) -> bytes:
    """A tiny statistics file whose mean declares a huge shape (numpy's own reduction forms)."""
    reconstruct = Name("numpy._core.multiarray", "_reconstruct")
    frombuffer = Name("numpy._core.numeric", "_frombuffer")
    f8 = np.dtype("f8")
    shape = (rng.choice((1 << 28, 1 << 31, 1 << 40, 2**62)),)
    which = rng.randrange(3)
    if which == 0:  # _reconstruct allocating the shape itself
        mean = Call(reconstruct, (Name("numpy", "ndarray"), shape, b"b"))
    elif which == 1:  # BUILD declaring the shape with a few bytes of data
        mean = Call(reconstruct, (Name("numpy", "ndarray"), (0,), b"b"))
        mean = _Built(mean, (1, shape, f8, False, b"\0" * 8))
    else:
        mean = Call(frombuffer, (b"\0" * 8, f8, shape, "C"))
    return dumps(vecnormalize(mean, np.ones(OBS)), 4)


class _Built:
    """`obj` followed by BUILD with `state` (an array's state after `_reconstruct`)."""

    def __init__(self, obj: Any, state: Any):
        self.obj, self.state = obj, state


def _save_built(self: _Pickler, obj: _Built) -> None:
    self.save(obj.obj)
    self.save(obj.state)
    self.write(pickle.BUILD)


_Pickler.dispatch = dict(pickle._Pickler.dispatch)
_Pickler.dispatch[_Built] = _save_built


def void_dtype_with_object_field(where: str = "norm_obs") -> bytes:
    """Statistics whose `where` (norm_obs, or obs_rms.mean) is an array of a void dtype that a
    BUILD gave an object field while its flags stay 0 (numpy then reads pointers from the file)."""
    reconstruct = Name("numpy._core.multiarray", "_reconstruct")
    void = _Built(
        Call(Name("numpy", "dtype"), ("V8", False, True)),
        (3, "|", None, ("a",), {"a": (np.dtype("O"), 0)}, 8, 1, 0),
    )
    array = _Built(Call(reconstruct, (Name("numpy", "ndarray"), (0,), b"b")), (1, (1,), void, False, b"\x41" * 8))
    stats = vecnormalize(np.zeros(OBS), np.ones(OBS))
    if where == "norm_obs":
        stats.state["norm_obs"] = array
    else:
        stats.state["obs_rms"].state["mean"] = array
    return dumps(stats, 4)


def zip_mutation(rng: random.Random, data: bytes) -> bytes:
    members = zip_members(data)
    i = rng.randrange(len(members))
    name, body = members[i]
    move = rng.randrange(4)
    if move == 0:  # rename
        j = rng.randrange(len(name))
        members[i] = (name[:j] + rng.choice("xZ_.0/") + name[j + 1 :], body)
    elif move == 1:  # remove
        del members[i]
    elif move == 2:  # duplicate (a second member of the same name)
        members.insert(rng.randrange(len(members) + 1), (name, body[: len(body) // 2]))
    else:  # empty
        members[i] = (name, b"")
    return zip_bytes(members)


def code_payloads(marker: Path) -> list[bytes]:
    """Pickles that run code when loaded by an unrestricted unpickler: each creates `marker`."""
    touch = f"touch {marker}"
    write = f"open({str(marker)!r}, 'w').close()"
    return [
        b"cos\nsystem\n(V" + touch.encode() + b"\ntR.",
        dumps(Call(Name("posix", "system"), (touch,)), 2),
        dumps(Call(Name("builtins", "exec"), (write,)), 4),
    ]


def in_torch_zip(data: bytes, member: str, blob: bytes) -> bytes:
    return replace_member(data, lambda n: n.endswith(member), lambda _: blob)


def code_case(fmt: str, seed: bytes, marker: Path, variant: int) -> tuple[bytes, str]:
    """A file of format `fmt` that would run code at its `variant`-th place; (bytes, where)."""
    payloads = code_payloads(marker)
    payload = payloads[variant % len(payloads)]
    if fmt == "stats":
        places = ["the file", "obs_rms", "obs_rms.mean"]
        place = places[variant % len(places)]
        if place == "the file":
            return payload, place
        call = Call(Name("posix", "system"), (f"touch {marker}",))
        stats = vecnormalize(np.zeros(OBS), np.ones(OBS))
        if place == "obs_rms":
            stats.state["obs_rms"] = call
        else:
            stats.state["obs_rms"].state["mean"] = call
        return dumps(stats, 4), place
    if fmt == "sb3":
        places = ["_last_obs", "policy_kwargs", "policy_class", "policy.pth", "policy.pth data.pkl"]
        place = places[variant % len(places)]
        if place.startswith("policy.pth"):
            change = (lambda body: in_torch_zip(body, "data.pkl", payload)) if " " in place else (lambda _: payload)
            return replace_member(seed, lambda n: n == "policy.pth", change), place

        def edit(text: bytes) -> bytes:
            doc = json.loads(text)
            doc[place][":serialized:"] = base64.b64encode(payload).decode()
            return json.dumps(doc).encode()

        return replace_member(seed, lambda n: n == "data", edit), place
    if fmt == "cleanrl":
        places = ["data.pkl", "the file"]
        place = places[variant % len(places)]
        return (in_torch_zip(seed, "data.pkl", payload) if place == "data.pkl" else payload), place
    if fmt == "torchscript":
        places = ["data.pkl", "constants.pkl"]
        place = places[variant % len(places)]
        return in_torch_zip(seed, place, payload), place
    return pt2_code_case(seed, payload, variant)


def pt2_code_case(seed: bytes, payload: bytes, variant: int) -> tuple[bytes, str]:
    """The places a .pt2 unpickles without weights_only (torch 2.13's torch.export.load)."""
    places = ["weight use_pickle", "constant use_pickle", "legacy weights", "sample inputs"]
    place = places[variant % len(places)]
    members = zip_members(seed)
    root = members[0][0].split("/")[0]
    if place == "weight use_pickle":
        name = f"{root}/data/weights/model_weights_config.json"
        config = json.loads(dict(members)[name])
        first = next(iter(config["config"].values()))
        first["use_pickle"] = True
        members = [
            (n, json.dumps(config).encode() if n == name else payload if n.endswith(first["path_name"]) else b)
            for n, b in members
        ]
    elif place == "constant use_pickle":
        name = f"{root}/data/constants/model_constants_config.json"
        config = {
            "config": {"c": {"path_name": "tensor_0", "is_param": False, "use_pickle": True, "tensor_meta": None}}
        }
        members = [(n, json.dumps(config).encode() if n == name else b) for n, b in members]
        members.append((f"{root}/data/constants/tensor_0", payload))
    elif place == "legacy weights":
        members.append((f"{root}/data/weights/model.pt", payload))
    else:
        members = [(n, payload if n.endswith("sample_inputs/model.pt") else b) for n, b in members]
    return zip_bytes(members), place


def mutate(rng: random.Random, fmt: str, kind: str, seed: bytes) -> tuple[bytes, str]:
    """`seed` (of format `fmt`) mutated by `kind`; (bytes, a few words on what was done)."""
    if kind == "seed":
        return seed, "unmutated"
    if kind == "flip":
        if fmt == "stats" or rng.random() < 0.5:
            return flip(rng, seed), "bytes flipped"
        # inside one member, the zip rewritten around it (its CRC right): what a CRC check cannot catch
        name = rng.choice([n for n, body in zip_members(seed) if body])
        return replace_member(seed, lambda n: n == name, lambda b: flip(rng, b)), f"bytes flipped in {name}"
    if kind == "truncate":
        n = rng.randrange(len(seed))
        return seed[:n], f"cut at {n} of {len(seed)}"
    if kind == "zip":
        return zip_mutation(rng, seed), "zip member renamed, removed, duplicated or emptied"
    if kind == "pickle_ops":
        return pickle_mutation(rng, fmt, seed, pickle_op), "a pickle opcode deleted, duplicated, swapped or inserted"
    if kind == "oversize":
        if fmt == "stats" and rng.random() < 0.5:
            return huge_shape_stats(rng), "an array of a huge shape"
        if fmt == "torch_export" or (fmt == "sb3" and rng.random() < 0.4):
            target = "model.json" if fmt == "torch_export" and rng.random() < 0.5 else None
            pick = (
                (lambda n: n == "data")
                if fmt == "sb3"
                else (lambda n: n.endswith(target or "model_weights_config.json"))
            )
            return replace_member(seed, pick, lambda t: oversize_json(rng, t)), "JSON integers made huge"
        return pickle_mutation(rng, fmt, seed, oversize_pickle), "pickle integers made huge"
    raise ValueError(kind)


def pickle_mutation(rng: random.Random, fmt: str, seed: bytes, change) -> bytes:
    """`change(rng, pickle)` applied to a pickle inside `seed`."""
    if fmt == "stats":
        if change is pickle_op and rng.random() < 0.2:
            return void_dtype_with_object_field(rng.choice(("norm_obs", "obs_rms.mean")))
        return change(rng, seed)
    if fmt == "sb3":
        if rng.random() < 0.5:
            entry = rng.choice(("_last_obs", "_last_original_obs", "policy_kwargs", "observation_space"))

            def edit(text: bytes) -> bytes:
                doc = json.loads(text)
                blob = base64.b64decode(doc[entry][":serialized:"])
                doc[entry][":serialized:"] = base64.b64encode(change(rng, blob)).decode()
                return json.dumps(doc).encode()

            return replace_member(seed, lambda n: n == "data", edit)
        member = rng.choice(("policy.pth", "critic.optimizer.pth"))
        return replace_member(
            seed,
            lambda n: n == member,
            lambda b: replace_member(b, lambda n: n.endswith("data.pkl"), lambda p: change(rng, p)),
        )
    if fmt == "torchscript":
        member = rng.choice(("data.pkl", "constants.pkl"))
        return replace_member(seed, lambda n: n.endswith(member), lambda p: change(rng, p))
    if fmt == "torch_export":
        inner = lambda b: replace_member(b, lambda n: n.endswith("data.pkl"), lambda p: change(rng, p))  # noqa: E731
        return replace_member(seed, lambda n: n.endswith("sample_inputs/model.pt"), inner)
    return replace_member(seed, lambda n: n.endswith("data.pkl"), lambda p: change(rng, p))


def kinds_of(fmt: str) -> tuple[str, ...]:
    return tuple(k for k in KINDS if not (fmt == "stats" and k == "zip"))


def make_cases(seeds: dict[str, Path], n: int, seed: int, folder: Path) -> list[dict]:
    """`n` cases, formats and kinds taken in turn (so any prefix covers them evenly), each file
    written to its own folder under `folder` (where its marker would appear)."""
    rng = random.Random(seed)
    pairs = [(fmt, kind) for kind in KINDS for fmt in FORMATS if kind in kinds_of(fmt)]
    raw = {fmt: path.read_bytes() for fmt, path in seeds.items()}
    variants = {fmt: 0 for fmt in FORMATS}
    cases = []
    for i in range(n):
        fmt, kind = pairs[i % len(pairs)]
        case_dir = folder / f"case{i:05d}"
        case_dir.mkdir(parents=True)
        marker = case_dir / "code_ran"
        if kind == "code":
            data, what = code_case(fmt, raw[fmt], marker, variants[fmt])
            variants[fmt] += 1
            what = f"would run code: {what}"
        else:
            data, what = mutate(rng, fmt, kind, raw[fmt])
        path = case_dir / SEED_FILES[fmt]
        path.write_bytes(data)
        cases.append({"id": i, "format": fmt, "kind": kind, "what": what, "file": str(path), "marker": str(marker)})
    return cases


# -- the server and its children ------------------------------------------------------------------


def fuzz_spec():
    from pipeline.core.envs import EnvSpec

    return EnvSpec("fuzz-v0", OBS, ACT, 2, (-1.0,) * ACT, (1.0,) * ACT, 40)


def read_case(fmt: str, path: str, spec) -> None:
    from pipeline.interop.readers import read_policy
    from pipeline.interop.vecnorm import read_vecnormalize

    if fmt == "stats":
        read_vecnormalize(path)
    else:
        read_policy(path, fmt, spec)


def vm_bytes() -> int:
    """This process's address space (VmSize), in bytes."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmSize:"):
            return int(line.split()[1]) << 10
    raise RuntimeError("no VmSize in /proc/self/status")


def rss_bytes() -> int:
    return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def child(case: dict, spec, headroom: int, result: Path) -> None:
    """In the forked child: limits, the read, the outcome written to `result`; never returns."""
    from pipeline.core.artifacts import ArtifactError

    code = 0
    try:
        (result.parent / "start_rss").write_text(str(rss_bytes()))
        log = os.open(Path(case["file"]).parent / "output.txt", os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
        os.dup2(log, 1)
        os.dup2(log, 2)
        limit = vm_bytes() + headroom
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
        resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
        try:
            read_case(case["format"], case["file"], spec)
            out = {"outcome": "accepted"}
        except ArtifactError as exc:
            out = {"outcome": "refused", "message": str(exc)}
        result.write_text(json.dumps(out))
    except BaseException:  # an uncaught exception of the read: a crash (its traceback goes to output.txt)
        import traceback

        traceback.print_exc()
        code = 3
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)


def run_case(case: dict, spec, headroom: int, timeout: float, server_rss: int) -> dict:
    result = Path(case["file"]).parent / "result.json"
    pid = os.fork()
    if pid == 0:
        child(case, spec, headroom, result)
    start, hung, pause = time.monotonic(), False, 0.002
    while True:
        done, status, usage = os.wait4(pid, os.WNOHANG)
        if done:
            break
        if time.monotonic() - start > timeout:
            os.kill(pid, signal.SIGKILL)
            _, status, usage = os.wait4(pid, 0)
            hung = True
            break
        time.sleep(pause)
        pause = min(pause * 1.5, 0.05)
    seconds = time.monotonic() - start
    out = {"id": case["id"], "seconds": round(seconds, 3), "maxrss_kb": usage.ru_maxrss}
    start = result.parent / "start_rss"
    start_kb = int(start.read_text()) // 1024 if start.exists() else server_rss // 1024
    out["growth_kb"] = max(0, usage.ru_maxrss - start_kb)  # what the read added to the child's resident pages
    out["code_ran"] = Path(case["marker"]).exists()
    output = Path(case["file"]).parent / "output.txt"
    tail = output.read_text(errors="replace").strip().splitlines()[-1:] if output.exists() else []
    if hung:
        return out | {"outcome": "hang", "detail": f"killed after {timeout} s"}
    if os.WIFSIGNALED(status):
        sig = signal.Signals(os.WTERMSIG(status)).name
        return out | {"outcome": "crash", "detail": f"signal {sig}", "tail": tail}
    if os.WEXITSTATUS(status) != 0 or not result.exists():
        return out | {"outcome": "crash", "detail": f"exit {os.WEXITSTATUS(status)}", "tail": tail}
    got = json.loads(result.read_text())
    if got["outcome"] == "refused":
        message = got["message"]
        if "\n" in message:
            return out | {"outcome": "crash", "detail": "a refusal of several lines", "tail": message.splitlines()[:3]}
        named = case["file"] in message
        return out | {"outcome": "refused", "message": message[:300], "names_file": named}
    return out | {"outcome": "accepted"}


def serve(cases_file: Path, results_file: Path, headroom: int, timeout: float, seeds: dict[str, str]) -> None:
    """The server: import once, read every seed once (lazy imports done), then fork a child per case."""
    import torch

    torch.set_num_threads(1)
    spec = fuzz_spec()
    warm = {}
    for fmt, path in seeds.items():  # also checks that every seed is a valid file of its format
        read_case(fmt, path, spec)
        warm[fmt] = "accepted"
    server_rss = rss_bytes()
    with results_file.open("w") as out:
        out.write(json.dumps({"server_rss_kb": server_rss // 1024, "seeds": warm}) + "\n")
        for line in cases_file.read_text().splitlines():
            case = json.loads(line)
            out.write(json.dumps(run_case(case, spec, headroom, timeout, server_rss) | {"file": case["file"]}) + "\n")
            out.flush()


# -- the driver -----------------------------------------------------------------------------------


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return "unknown"


def summarize(cases: list[dict], results: list[dict]) -> dict:
    by_id = {r["id"]: r for r in results}
    rows: dict[str, dict] = {key: {} for key in ("all", *FORMATS, *(f"kind:{k}" for k in KINDS))}
    for case in cases:
        r = by_id[case["id"]]
        for key in ("all", case["format"], f"kind:{case['kind']}"):
            row = (
                rows[key]
                or rows[key].update(
                    {
                        "cases": 0,
                        "refused": 0,
                        "accepted": 0,
                        "crash": 0,
                        "hang": 0,
                        "code_ran": 0,
                        "peak_rss_mb": 0.0,
                        "peak_growth_mb": 0.0,
                        "refused_without_file_name": 0,
                    }
                )
                or rows[key]
            )
            row["cases"] += 1
            row[r["outcome"]] += 1
            row["code_ran"] += int(r["code_ran"])
            row["refused_without_file_name"] += int(r["outcome"] == "refused" and not r["names_file"])
            row["peak_rss_mb"] = max(row["peak_rss_mb"], round(r["maxrss_kb"] / 1024, 1))
            row["peak_growth_mb"] = max(row["peak_growth_mb"], round(r["growth_kb"] / 1024, 1))
    return {key: row for key, row in rows.items() if row}


def table(rows: dict[str, dict]) -> str:
    cols = ("cases", "refused", "accepted", "crash", "hang", "code_ran", "peak_rss_mb", "peak_growth_mb")
    lines = [f"{'':22}" + "".join(f"{c:>15}" for c in cols)]
    for key, row in rows.items():
        lines.append(f"{key:22}" + "".join(f"{row[c]:>15}" for c in cols))
    return "\n".join(lines)


def findings(cases: list[dict], results: list[dict], keep: Path | None) -> list[dict]:
    by_id = {c["id"]: c for c in cases}
    out = []
    for r in results:
        case = by_id[r["id"]]
        if (
            r["outcome"] in ("crash", "hang")
            or r["code_ran"]
            or (case["kind"] == "code" and r["outcome"] == "accepted")
        ):
            item = {k: case[k] for k in ("id", "format", "kind", "what")} | {
                k: r.get(k) for k in ("outcome", "detail", "tail", "code_ran", "message")
            }
            if keep is not None:
                keep.mkdir(parents=True, exist_ok=True)
                dest = keep / f"case{r['id']:05d}_{Path(case['file']).name}"
                shutil.copy(case["file"], dest)
                item["kept"] = str(dest)
            out.append(item)
    return out


def run(args: argparse.Namespace) -> dict:
    work = Path(tempfile.mkdtemp(prefix="fuzz_imports_"))
    try:
        t0 = time.perf_counter()
        seeds = build_seeds(work / "seeds")
        cases = make_cases(seeds, args.cases, args.seed, work / "cases")
        shards = [cases[i :: args.workers] for i in range(args.workers)]
        procs = []
        for i, shard in enumerate(shards):
            (work / f"cases{i}.jsonl").write_text("".join(json.dumps(c) + "\n" for c in shard))
            cmd = [sys.executable, __file__, "--serve", str(work / f"cases{i}.jsonl"), str(work / f"results{i}.jsonl")]
            cmd += ["--memory-mb", str(args.memory_mb), "--timeout", str(args.timeout)]
            cmd += ["--seeds", json.dumps({k: str(v) for k, v in seeds.items()})]
            env = os.environ | {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
            procs.append(subprocess.Popen(cmd, env=env))
        codes = [p.wait() for p in procs]
        results, server = [], []
        for i in range(args.workers):
            lines = (
                (work / f"results{i}.jsonl").read_text().splitlines() if (work / f"results{i}.jsonl").exists() else []
            )
            server += [json.loads(lines[0])] if lines else []
            results += [json.loads(line) for line in lines[1:]]
        if any(codes) or len(results) != len(cases):
            raise SystemExit(f"fuzz server failed (exit {codes}; {len(results)} of {len(cases)} cases run)")
        rows = summarize(cases, results)
        wall = time.perf_counter() - t0
        return {
            "command": " ".join([Path(sys.executable).name, *sys.argv]),
            "cpu": cpu_model(),
            "versions": versions(),
            "cases": len(cases),
            "seed": args.seed,
            "memory_limit_mb": args.memory_mb,
            "timeout_s": args.timeout,
            "workers": args.workers,
            "wall_s": round(wall, 1),
            "server_rss_mb": [round(s["server_rss_kb"] / 1024, 1) for s in server],
            "summary": rows,
            "findings": findings(cases, results, Path(args.keep) if args.keep else None),
        }
    finally:
        shutil.rmtree(work, ignore_errors=True)


def versions() -> dict[str, str]:
    import torch

    return {"python": sys.version.split()[0], "numpy": np.__version__, "torch": torch.__version__}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--cases", type=int, default=2000, help="mutated inputs to try (default 2000)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the mutations (default 0)")
    parser.add_argument("--workers", type=int, default=1, help="server processes, each forking one child at a time")
    parser.add_argument("--memory-mb", type=int, default=1024, help="address space a child may add (RLIMIT_AS)")
    parser.add_argument("--timeout", type=float, default=30.0, help="seconds before a child counts as a hang")
    parser.add_argument("--out", default="fuzz_imports.json", help="JSON report (default fuzz_imports.json)")
    parser.add_argument("--keep", default=None, help="folder to copy the files of crashes, hangs and code runs to")
    parser.add_argument("--serve", nargs=2, metavar=("CASES", "RESULTS"), help=argparse.SUPPRESS)
    parser.add_argument("--seeds", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.serve:
        serve(Path(args.serve[0]), Path(args.serve[1]), args.memory_mb << 20, args.timeout, json.loads(args.seeds))
        return 0
    if args.cases < 1 or args.workers < 1:
        parser.error("--cases and --workers must be at least 1")
    report = run(args)
    Path(args.out).write_text(json.dumps(report, indent=1) + "\n")
    print(table(report["summary"]))
    print(f"{report['cases']} cases in {report['wall_s']} s on {report['cpu']}; report in {args.out}")
    for item in report["findings"]:
        print(
            f"finding: case {item['id']} {item['format']} {item['kind']} ({item['what']}): {item['outcome']}"
            f"{', code ran' if item['code_ran'] else ''} {item.get('detail') or ''}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
