"""A TorchScript archive checked before `torch.jit.load` reads it: every tensor its pickles
declare fits in the record that holds its data.

`torch.jit.load` (torch 2.13) trusts the archive's pickles (`data.pkl`, `constants.pkl`) for
the size of each storage: a record emptied or cut short while the pickle still declares its
elements makes it read past the record's end and crash the interpreter (SIGSEGV: found by
benchmarks/fuzz_imports.py, three of 412 TorchScript cases of 2,000). This reads those pickles
without running anything (a pure-Python unpickler whose names are all inert recorders; the
TorchScript loader itself imports no Python code from them) and refuses, with one line naming
the file, any storage whose record is missing or smaller than its elements, and any tensor whose
offset, sizes and strides reach past its storage. The code in the archive (`code/`) is a program
and stays one: what it computes is checked by the import on a probe batch, not here.
"""

from __future__ import annotations

import io
import math
import pickle
import zipfile
from pathlib import Path
from typing import Any

from pipeline.core.artifacts import ArtifactError, first_line

MAX_OPCODES = 1_000_000  # a small policy's data.pkl runs a few hundred
MAX_PICKLE_BYTES = 16 << 20  # a policy's data.pkl or constants.pkl is a few KB (its tensors are records)
ITEMSIZE = {
    "BoolStorage": 1,
    "ByteStorage": 1,
    "CharStorage": 1,
    "ShortStorage": 2,
    "IntStorage": 4,
    "LongStorage": 8,
    "HalfStorage": 2,
    "BFloat16Storage": 2,
    "FloatStorage": 4,
    "DoubleStorage": 8,
    "ComplexFloatStorage": 8,
    "ComplexDoubleStorage": 16,
}
REBUILDERS = ("torch._utils._rebuild_tensor_v2", "torch._utils._rebuild_tensor")


class _Unfit(Exception):
    """What the check refuses (the message says what, for the one line)."""


class _Recorder:
    """Whatever a name of the pickle stands for: called, built or set, it keeps nothing and runs nothing."""

    qualname = ""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        pass

    def __call__(self, *args: Any, **kwargs: Any) -> "_Recorder":
        return _Recorder()

    def __setstate__(self, state: Any) -> None:
        pass

    def __setitem__(self, key: Any, value: Any) -> None:
        pass

    def append(self, item: Any) -> None:
        pass

    def extend(self, items: Any) -> None:
        pass


class _Storage:
    def __init__(self, key: str, numel: int):
        self.key, self.numel = key, numel


def _counted(op: Any) -> Any:
    def run(self: "_Reader") -> None:
        self.opcodes += 1
        if self.opcodes > MAX_OPCODES:
            raise _Unfit(f"runs more than {MAX_OPCODES} pickle opcodes")
        op(self)

    return run


def _reduce(self: "_Reader") -> None:
    """REDUCE: nothing is called; the arguments of a tensor rebuilder are checked against its storage."""
    args = self.stack.pop()
    func = self.stack[-1]
    if getattr(func, "qualname", "") in REBUILDERS and type(args) is tuple and len(args) >= 4:
        _check_view(*args[:4])
    self.stack[-1] = _Recorder()


class _Inert(_Recorder):
    """A dict or set of the pickle: its items are taken and dropped, never hashed, so that keys
    which all hash alike cost no quadratic inserts (issue 57: 40,000 such keys took 9 s). The
    check needs no container's contents: tensors are checked where they are rebuilt."""

    def add(self, item: Any) -> None:
        pass


def _inert_dict(self: "_Reader") -> None:  # EMPTY_DICT, EMPTY_SET
    self.append(_Inert())


def _inert_from_mark(self: "_Reader") -> None:  # DICT, FROZENSET: the marked items, dropped
    self.pop_mark()
    self.append(_Inert())


def _inert_additems(self: "_Reader") -> None:  # ADDITEMS: items into a set, dropped
    self.pop_mark()


class _Reader(pickle._Unpickler):  # pure Python: a dict memo, its opcode table replaceable, nothing imported
    dispatch = {code: _counted(op) for code, op in pickle._Unpickler.dispatch.items()}
    dispatch[pickle.REDUCE[0]] = _counted(_reduce)
    for _op, _fn in (
        (pickle.EMPTY_DICT, _inert_dict),
        (pickle.EMPTY_SET, _inert_dict),
        (pickle.DICT, _inert_from_mark),
        (pickle.FROZENSET, _inert_from_mark),
        (pickle.ADDITEMS, _inert_additems),
    ):
        dispatch[_op[0]] = _counted(_fn)

    def __init__(self, data: bytes, sizes: dict[str, int], folder: str):
        super().__init__(io.BytesIO(data))
        self.sizes, self.folder, self.opcodes = sizes, folder, 0

    def find_class(self, module: str, name: str) -> Any:
        return type("Name", (_Recorder,), {"qualname": f"{module}.{name}"})

    def persistent_load(self, pid: Any) -> _Storage:
        # ('storage', storage type, key, location, numel), as torch.jit.save writes it
        if type(pid) is not tuple or len(pid) != 5 or pid[0] != "storage":
            raise _Unfit("holds a persistent id other than a storage")
        kind, key, numel = pid[1], pid[2], pid[4]
        name = getattr(kind, "qualname", "").rpartition(".")[2]
        if name not in ITEMSIZE or type(key) is not str or type(numel) is not int or numel < 0:
            raise _Unfit(f"declares a storage of type {name[:40] or type(kind).__name__} (expected a numeric storage)")
        record = f"{self.folder}/{key}"
        need = numel * ITEMSIZE[name]
        if self.sizes.get(record, -1) < need:
            have = "no record" if record not in self.sizes else f"{self.sizes[record]} bytes"
            raise _Unfit(f"declares {need} bytes for storage {key[:40]!r} ({numel} x {name}); its record has {have}")
        return _Storage(key, numel)


def _str_key(key: Any) -> None:
    # str keys (parameter names; salted hashes) or the small non-negative ints an optimizer's state
    # is keyed by (parameter indices): distinct ints below 2**61 - 1 hash to themselves, so no two collide
    if type(key) is str or (type(key) is int and 0 <= key < 1 << 31):
        return
    raise _Unfit(f"uses {_brief_key(key)} as a dict key (a state dict has only str keys, an optimizer's small ints)")


def _brief_key(key: Any) -> str:
    return f"the int {key}"[:60] if type(key) is int else f"a {type(key).__name__}"


def _keyed_setitem(self: "_Reader") -> None:  # SETITEM of a torch.save pickle: a str key, then as ever
    _str_key(self.stack[-2])
    pickle._Unpickler.dispatch[pickle.SETITEM[0]](self)


def _keyed_setitems(self: "_Reader") -> None:  # SETITEMS: every key a str, checked before any is set
    for key in self.stack[::2]:  # the pure-Python unpickler's stack holds just the items since the MARK
        _str_key(key)
    pickle._Unpickler.dispatch[pickle.SETITEMS[0]](self)


def _keyed_dict(self: "_Reader") -> None:  # DICT: the marked keys checked, the items dropped
    items = self.pop_mark()
    for key in items[::2]:
        _str_key(key)
    self.append(_Inert())


class _StateDictReader(_Reader):
    """The reader for a torch.save zip (a CleanRL checkpoint, an SB3 policy.pth or optimizer): a
    state dict's keys are parameter names (an optimizer's, parameter indices), so any other dict
    key is refused at once. Its dicts become
    real ones in torch.load's own unpickler after this check, where keys crafted to collide would
    cost quadratic inserts (issue 57: 40,000 such keys, 10.6 s); str hashes are salted per process,
    so str keys cannot be made to collide."""

    dispatch = dict(_Reader.dispatch)
    for _op, _fn in ((pickle.SETITEM, _keyed_setitem), (pickle.SETITEMS, _keyed_setitems), (pickle.DICT, _keyed_dict)):
        dispatch[_op[0]] = _counted(_fn)


def _check_view(storage: Any, offset: Any, size: Any, stride: Any) -> None:
    """A tensor `size`/`stride` from `offset` stays inside its storage's elements."""
    if not isinstance(storage, _Storage):
        raise _Unfit("rebuilds a tensor from something other than a storage")
    dims = (size, stride)
    if type(offset) is not int or not all(type(d) is tuple and all(type(x) is int for x in d) for d in dims):
        raise _Unfit(f"rebuilds a tensor of storage {storage.key!r} with an offset, sizes or strides not ints")
    if len(size) != len(stride) or offset < 0 or any(x < 0 for x in size + stride):
        raise _Unfit(f"rebuilds a tensor of storage {storage.key!r} with negative or mismatched sizes and strides")
    if math.prod(size) and offset + sum((n - 1) * s for n, s in zip(size, stride)) >= storage.numel:
        raise _Unfit(f"rebuilds a tensor of {len(size)} dims reaching past the {storage.numel} elements of its storage")


def check_torchscript(data: bytes, path: Path | str, what: str = "TorchScript") -> None:
    """Refuse (ArtifactError, one line naming `path`) a TorchScript archive `data` whose pickles
    declare tensors that its records cannot hold; return None for one torch.jit.load may read.
    A torch.save zip (a CleanRL checkpoint, an SB3 policy.pth) has the same layout, so its
    reader runs this too before torch.load, with `what` naming its format in the messages."""
    try:
        zf = zipfile.ZipFile(io.BytesIO(data))
        sizes = {info.filename: info.file_size for info in zf.infolist()}
    except Exception as exc:  # a damaged central directory raises BadZipFile, ValueError, ...
        raise ArtifactError(f"{path}: not a {what} archive (not a readable zip: {first_line(exc)})") from None
    pickles = [name for name in sizes if name.count("/") == 1 and name.endswith(("/data.pkl", "/constants.pkl"))]
    if not any(name.endswith("/data.pkl") for name in pickles):
        raise ArtifactError(f"{path}: not a {what} archive (no data.pkl)")
    for name in pickles:
        root, member = name.split("/")
        folder = f"{root}/{'data' if member == 'data.pkl' else 'constants'}"
        if sizes[name] > MAX_PICKLE_BYTES:  # declared size, before a byte is inflated
            raise ArtifactError(
                f"{path}: {what} {member} declares {sizes[name]} bytes; refused above {MAX_PICKLE_BYTES}"
            )
        try:
            with zf.open(name) as fh:
                raw = fh.read(MAX_PICKLE_BYTES + 1)  # a header that lies about the size inflates no further
            if len(raw) > MAX_PICKLE_BYTES:
                raise _Unfit(f"inflates past {MAX_PICKLE_BYTES} bytes")
            (_Reader if what == "TorchScript" else _StateDictReader)(raw, sizes, folder).load()
        except _Unfit as exc:
            raise ArtifactError(f"{path}: {what} {member} {exc}; refused before torch reads it") from None
        except Exception as exc:  # damaged bytes: say so in one line (torch.jit.load would only fail later)
            raise ArtifactError(f"{path}: {what} {member} is not a readable pickle ({first_line(exc)})") from None
