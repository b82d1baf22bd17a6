"""Observation statistics of a model trained under Stable-Baselines3's `VecNormalize`, read
without running the code a pickle names (docs/import_export.md, "Models trained with
normalised observations").

SB3 saves `VecNormalize` beside the model as a pickle of the wrapper (`vecnormalize.pkl` in
rl-zoo3's layout): its `__getstate__` drops the wrapped env, so what remains is the wrapper's
settings and running statistics, `obs_rms` (a `RunningMeanStd`: `mean`, `var`, `count`, numpy
float64 arrays), `epsilon`, `clip_obs`, `norm_obs`, `norm_reward` (and `ret_rms`, the spaces,
their random generators). The policy it trained saw
`clip((obs - mean) / sqrt(var + epsilon), -clip_obs, clip_obs)`.

Why a restricted `pickle.Unpickler` and not a walk of the opcodes: a pickle obtains every
callable it runs (REDUCE, NEWOBJ, INST, OBJ, the EXT codes) by name through
`Unpickler.find_class`, and BUILD only calls `__setstate__` of an object made by one of them,
so a `find_class` that allow-lists names is Python's own gate ("Restricting Globals" in the
pickle docs); persistent ids are refused by the base class. The gate here lets through only
numpy's array, dtype and scalar reconstruction (plain data, needed for the statistics: each
name is answered with a checked rebuilder of this module, see below); every
name of SB3, Gymnasium's or gym's spaces and numpy.random becomes an inert stand-in that
records the arguments and state the pickle gives it and runs nothing (their modules are not
even imported). Any other name (os.system, builtins.eval, ...) stops the read at once with one
line naming the file and the name, before anything it would call exists. A stack machine over
`pickletools.genops` would re-implement the memo and every opcode's stack effect to find the
same names, with more room for a mistake.

The unpickler is Python's own pure-Python one (`pickle._Unpickler`), for two reasons the C one
cannot give: its dispatch table can be replaced, so BUILD (which calls `__setstate__` on
whatever object is on the stack) and SETITEM(S)/APPEND(S)/ADDITEMS reach only the objects this
gate made, and its memo is a dict (the C unpickler grows an array to the largest memo index a
file names: a 9-byte pickle can ask for 32 GB). numpy's own names are never handed to the
stream: `numpy.dtype` becomes a constructor of inert dtype tokens, taken only for a short list of
plain numeric types with a BUILD state that says nothing more than a byte order (numpy lets a
BUILD on a dtype add fields, an object field among them, while its flags still say "no Python
objects": arrays of such a dtype read addresses from the file and crash the interpreter), and
every array is rebuilt here, as a plain ndarray of one of those dtypes, with at most MAX_NDIM
dimensions, after its size is checked against what is left of the file's own size (its bytes
come from the file, so no true array is bigger) and an absolute cap: a 420-byte file cannot
allocate gigabytes. The number of opcodes run is capped too (a real statistics file runs a few
hundred), which bounds the Python objects a file can make. Every error of the unpickler or numpy
on hostile bytes (OverflowError, MemoryError, ValueError, struct.error, ...) ends in one line
naming the file.
"""

from __future__ import annotations

import io
import math
import pickle
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from pipeline.core.artifacts import ArtifactError, first_line

MAX_BYTES = 16 << 20  # a VecNormalize file of a flat Box is a few kB; refuse anything huge unread
MAX_ARRAY_BYTES = 16 << 20  # absolute cap on the bytes of all arrays of one pickle (the file's size caps them too)
MAX_OPCODES = 100_000  # a real VecNormalize pickle runs a few hundred, an SB3 `_last_obs` a few dozen
MAX_NDIM = 8
MAX_DIM = 1 << 31
# the dtypes an array or scalar may have: numbers, as numpy pickles them (`np.dtype("f8").__reduce__()`)
PLAIN_DTYPES = frozenset({"b1", "i1", "i2", "i4", "i8", "u1", "u2", "u4", "u8", "f2", "f4", "f8"})
BYTE_ORDERS = frozenset({"<", ">", "|", "="})
VEC_NORMALIZE = "stable_baselines3.common.vec_env.vec_normalize.VecNormalize"
RUNNING_MEAN_STD = "stable_baselines3.common.running_mean_std.RunningMeanStd"
# names whose stand-in is inert: SB3's classes, the spaces a wrapper pickles, their generators
INERT_PREFIXES = ("stable_baselines3.", "gymnasium.spaces.", "gym.spaces.", "numpy.random.")


class _Unsafe(Exception):
    """What the gate refuses of a pickle other than a name (the message says what, for the one line)."""


class _Refused(Exception):
    def __init__(self, module: str, name: str):
        super().__init__(f"{module}.{name}")


def _brief(value: Any) -> str:
    """A short, safe description of a value read from a pickle, for an error line: the repr of a
    small plain value, else its type (never the repr of a hostile object, a huge int or a deep list)."""
    if value is None or isinstance(value, (bool, float, np.bool_, np.floating)):
        return repr(value)[:40]
    if isinstance(value, (int, np.integer)):
        return repr(int(value)) if abs(int(value)) < 10**30 else "a huge int"
    if isinstance(value, str):
        return repr(value[:40])
    return f"a {type(value).__name__}"


class _Dtype:
    """What the pickle gets for `numpy.dtype(code, align, copy)`: a token of one of PLAIN_DTYPES,
    whose BUILD state may set the byte order and nothing else; the real dtype is made from it
    only where an array or scalar is rebuilt here."""

    __slots__ = ("code", "order")

    def __init__(self, code: str):
        self.code, self.order = code, "="

    def __setstate__(self, state: Any) -> None:
        # numpy's state of a plain dtype: (3, byte order, subarray, names, fields, elsize, alignment, flags)
        plain = type(state) is tuple and len(state) == 8 and state[0] == 3 and state[2:] == (None,) * 3 + (-1, -1, 0)
        if not plain or not isinstance(state[1], str) or state[1] not in BYTE_ORDERS:
            raise _Unsafe(
                f"gives dtype {self.code} a state other than a byte order (fields, a subarray, flags, metadata)"
            )
        self.order = state[1]

    def numpy(self) -> np.dtype:
        return np.dtype(self.code).newbyteorder(self.order) if self.order in "<>" else np.dtype(self.code)


class _DtypeName:
    """What the pickle gets for the name numpy.dtype: called (or built with NEWOBJ), it makes a
    `_Dtype` token of a plain numeric type and refuses every other (void, structured, object,
    strings, datetimes)."""

    def __new__(cls, code: Any = None, align: Any = False, copy: Any = True) -> _Dtype:  # type: ignore[misc]
        if not isinstance(code, str) or code not in PLAIN_DTYPES:
            raise _Unsafe(f"asks for dtype {_brief(code)}; only plain numbers ({', '.join(sorted(PLAIN_DTYPES))})")
        if align not in (0, 1) or copy not in (0, 1):
            raise _Unsafe(f"asks for dtype {code} with align={_brief(align)}, copy={_brief(copy)}")
        return _Dtype(code)


class _NdarrayName:
    """What the pickle gets for the name numpy.ndarray: only a token for `_reconstruct`'s first
    argument. Called itself it refuses: `ndarray(shape, dtype, buffer=...)` would build an array
    from the pickle's raw bytes outside the checks here."""

    def __new__(cls, *args: Any, **kwargs: Any) -> Any:
        raise _Unsafe("calls numpy.ndarray directly: statistics are rebuilt, never constructed")


def _shape(shape: Any) -> tuple[int, ...]:
    """`shape` as a tuple of at most MAX_NDIM plain ints in [0, MAX_DIM)."""
    if type(shape) not in (tuple, list) or len(shape) > MAX_NDIM:
        what = f"{len(shape)} dimensions" if type(shape) in (tuple, list) else _brief(shape)
        raise _Unsafe(f"declares an array shape of {what}; expected a tuple of at most {MAX_NDIM} sizes")
    if not all(type(d) is int and 0 <= d < MAX_DIM for d in shape):
        bad = next(d for d in shape if not (type(d) is int and 0 <= d < MAX_DIM))
        raise _Unsafe(f"declares an array dimension of {_brief(bad)}; expected an int in [0, {MAX_DIM})")
    return tuple(shape)


def _dtype(token: Any) -> np.dtype:
    if type(token) is not _Dtype:
        raise _Unsafe(f"gives an array or scalar the dtype {_brief(token)}, not one built by numpy.dtype")
    return token.numpy()


class Inert:
    """The stand-in for one allowed name: called or built, it keeps what it was given."""

    name = ""

    def __new__(cls, *args: Any, **kwargs: Any) -> "Inert":
        obj = super().__new__(cls)
        obj.args, obj.kwargs, obj.state = args, kwargs, None
        return obj

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        pass

    def __setstate__(self, state: Any) -> None:
        self.state = state


def _counted(op: Any) -> Any:
    def run(self: "_RestrictedUnpickler") -> None:
        self.opcodes += 1
        if self.opcodes > MAX_OPCODES:
            raise _Unsafe(f"runs more than {MAX_OPCODES} pickle opcodes (a file of statistics runs a few hundred)")
        op(self)

    return run


def _load_build(self: "_RestrictedUnpickler") -> None:
    """BUILD: the state of an inert stand-in, a dtype token or an array rebuilt here; nothing else."""
    state = self.stack.pop()
    inst = self.stack[-1]
    if isinstance(inst, Inert) or type(inst) is _Dtype:
        inst.__setstate__(state)
    elif type(inst) is np.ndarray and any(inst is a for a in self.rebuilt):
        self.set_array_state(inst, state)
    else:
        raise _Unsafe(f"sets the state of a {type(inst).__name__} (only arrays rebuilt and inert names take one)")


def _container(self: "_RestrictedUnpickler", kind: type, opcode: str) -> Any:
    target = self.stack[-1]
    if type(target) is not kind:
        raise _Unsafe(f"applies {opcode} to a {type(target).__name__}, not a {kind.__name__}")
    return target


def _load_append(self: "_RestrictedUnpickler") -> None:
    value = self.stack.pop()
    _container(self, list, "APPEND").append(value)


def _load_appends(self: "_RestrictedUnpickler") -> None:
    items = self.pop_mark()
    _container(self, list, "APPENDS").extend(items)


def _key(key: Any, opcode: str) -> Any:
    """A dict key or set item as a real statistics file has them: a str (attribute and field
    names). Anything else is refused before it is hashed, so keys crafted to collide (integers
    whose hashes all agree; str hashes are salted per process) cost no quadratic inserts (issue 57)."""
    if type(key) is not str:
        raise _Unsafe(f"uses a {type(key).__name__} as a {opcode} key (a file of statistics has only str keys)")
    return key


def _load_setitem(self: "_RestrictedUnpickler") -> None:
    value, key = self.stack.pop(), self.stack.pop()
    _container(self, dict, "SETITEM")[_key(key, "SETITEM")] = value


def _load_setitems(self: "_RestrictedUnpickler") -> None:
    items = self.pop_mark()
    target = _container(self, dict, "SETITEMS")
    if len(items) % 2:
        raise _Unsafe("gives SETITEMS an odd number of items")
    for i in range(0, len(items), 2):
        target[_key(items[i], "SETITEMS")] = items[i + 1]


def _load_dict(self: "_RestrictedUnpickler") -> None:
    items = self.pop_mark()
    if len(items) % 2:
        raise _Unsafe("gives DICT an odd number of items")
    self.append({_key(items[i], "DICT"): items[i + 1] for i in range(0, len(items), 2)})


def _load_frozenset(self: "_RestrictedUnpickler") -> None:
    self.append(frozenset(_key(x, "FROZENSET") for x in self.pop_mark()))


def _load_additems(self: "_RestrictedUnpickler") -> None:
    items = self.pop_mark()
    _container(self, set, "ADDITEMS").update(_key(x, "ADDITEMS") for x in items)


class _RestrictedUnpickler(pickle._Unpickler):  # the pure-Python unpickler: see the module's docstring
    dispatch = {code: _counted(op) for code, op in pickle._Unpickler.dispatch.items()}
    for _code, _op in (
        (pickle.BUILD, _load_build),
        (pickle.APPEND, _load_append),
        (pickle.APPENDS, _load_appends),
        (pickle.SETITEM, _load_setitem),
        (pickle.SETITEMS, _load_setitems),
        (pickle.ADDITEMS, _load_additems),
        (pickle.DICT, _load_dict),
        (pickle.FROZENSET, _load_frozenset),
    ):
        dispatch[_code[0]] = _counted(_op)
    del _code, _op

    def __init__(self, data: bytes):
        super().__init__(io.BytesIO(data))
        self._inert: dict[str, type[Inert]] = {}
        self.opcodes = 0
        self.budget = min(len(data), MAX_ARRAY_BYTES)  # bytes all arrays together may hold
        self.rebuilt: list[np.ndarray] = []  # arrays made by `_reconstruct`, which BUILD may fill
        self._numpy = {("numpy", "ndarray"): _NdarrayName, ("numpy", "dtype"): _DtypeName}
        for core in ("numpy.core", "numpy._core"):
            self._numpy[(f"{core}.multiarray", "_reconstruct")] = self.reconstruct
            self._numpy[(f"{core}.multiarray", "scalar")] = self.scalar
            self._numpy[(f"{core}.numeric", "_frombuffer")] = self.frombuffer

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in self._numpy:
            return self._numpy[(module, name)]
        if module.startswith(INERT_PREFIXES) and name.isidentifier():
            key = f"{module}.{name}"
            if key not in self._inert:
                self._inert[key] = type(name, (Inert,), {"name": key})
            return self._inert[key]
        raise _Refused(module, name)

    def spend(self, shape: tuple[int, ...], dtype: np.dtype) -> int:
        """Charge an array of `shape` and `dtype` to the budget, before anything is allocated."""
        nbytes = math.prod(shape) * dtype.itemsize
        if nbytes > self.budget:
            raise _Unsafe(
                f"declares an array of {nbytes} bytes (shape {shape}, {dtype}) with {self.budget} bytes left of the "
                f"file's size or the cap of {MAX_ARRAY_BYTES}; refused before allocating"
            )
        self.budget -= nbytes
        return nbytes

    def reconstruct(self, subtype: Any, shape: Any, placeholder: Any) -> np.ndarray:
        """numpy's `_reconstruct(ndarray, shape, b"b")`: the empty array a BUILD then fills."""
        if subtype is not _NdarrayName:
            raise _Unsafe("rebuilds an array as another type than numpy.ndarray")
        dtype = np.dtype(np.int8) if type(placeholder) is bytes and placeholder == b"b" else _dtype(placeholder)
        shape = _shape(shape)
        self.spend(shape, dtype)
        out = np.zeros(shape, dtype)
        self.rebuilt.append(out)
        return out

    def set_array_state(self, array: np.ndarray, state: Any) -> None:
        """numpy's array state ([1,] shape, dtype, is_fortran, raw bytes), checked, then set."""
        if type(state) is tuple and len(state) == 5 and state[0] == 1:
            state = state[1:]
        if type(state) is not tuple or len(state) != 4:
            raise _Unsafe("gives an array a state other than (version, shape, dtype, is_fortran, bytes)")
        shape, dtype, fortran, raw = _shape(state[0]), _dtype(state[1]), state[2], state[3]
        if fortran not in (0, 1) or type(raw) is not bytes:
            raise _Unsafe("gives an array a state whose data is not raw bytes of numbers")
        if len(raw) != math.prod(shape) * dtype.itemsize:
            raise _Unsafe(f"gives an array of shape {shape} and dtype {dtype} {len(raw)} bytes of data")
        self.spend(shape, dtype)
        np.ndarray.__setstate__(array, (1, shape, dtype, bool(fortran), raw))

    def frombuffer(self, buf: Any, dtype: Any, shape: Any, order: Any) -> np.ndarray:
        """numpy's `_frombuffer(bytes, dtype, shape, order)` (protocol 5), checked."""
        dtype, shape = _dtype(dtype), _shape(shape)
        if type(buf) not in (bytes, bytearray) or order not in ("C", "F"):
            raise _Unsafe("rebuilds an array from something other than bytes in C or F order")
        if len(buf) != math.prod(shape) * dtype.itemsize:
            raise _Unsafe(f"gives an array of shape {shape} and dtype {dtype} {len(buf)} bytes of data")
        self.spend(shape, dtype)
        return np.frombuffer(buf, dtype).reshape(shape, order=order)

    def scalar(self, dtype: Any, data: Any = None) -> Any:
        """numpy's `scalar(dtype, bytes)`: a number of a plain dtype from its bytes."""
        dtype = _dtype(dtype)
        if type(data) is not bytes or len(data) != dtype.itemsize:
            raise _Unsafe(f"gives a {dtype} scalar other than its {dtype.itemsize} bytes")
        return np.frombuffer(data, dtype)[0].copy()


def restricted_loads(data: bytes, path: Path, what: str) -> Any:
    """Unpickle `data` (of file `path`, described as `what`) through the allow-list above;
    ArtifactError with one line naming the file and the first name or thing refused, or the damage."""
    try:
        return _RestrictedUnpickler(data).load()
    except _Refused as exc:
        raise ArtifactError(
            f"{path}: {what} refers to {exc}, which a file of observation statistics does not need; refused "
            "unread (only numpy arrays and inert names of SB3, Gymnasium spaces and numpy.random are read)"
        ) from None
    except _Unsafe as exc:
        raise ArtifactError(f"{path}: {what} {first_line(exc)}; refused (statistics are arrays of numbers)") from None
    except RecursionError:
        raise ArtifactError(f"{path}: {what} nests too deep to be a file of observation statistics") from None
    except Exception as exc:  # hostile bytes make the unpickler or numpy raise any built-in error: all mean "damaged"
        raise ArtifactError(f"{path}: {what} is not a readable pickle ({first_line(exc)})") from None


class ObsStatistics(NamedTuple):
    """What a VecNormalize file says of the observations its policy saw."""

    norm_obs: bool  # False: the policy saw raw observations (mean and var are then None)
    mean: np.ndarray | None  # (obs_dim,) float64
    var: np.ndarray | None  # (obs_dim,) float64
    epsilon: float
    clip_obs: float
    norm_reward: bool  # recorded only: rewards do not reach the actor

    @property
    def std(self) -> np.ndarray:
        """sqrt(var + epsilon) in float64, as SB3 computes it."""
        return np.sqrt(self.var + self.epsilon)

    def normalize(self, obs: np.ndarray) -> np.ndarray:
        """What the policy saw for raw `obs` (..., obs_dim), in float64 (SB3's arithmetic)."""
        if not self.norm_obs:
            return np.asarray(obs, np.float64)
        return np.clip((obs - self.mean) / self.std, -self.clip_obs, self.clip_obs)

    def record(self) -> dict[str, Any]:
        """The metadata a slot records of them (no arrays: shapes and settings)."""
        shape = None if self.mean is None else list(self.mean.shape)
        return {
            "norm_obs": self.norm_obs,
            "norm_reward": self.norm_reward,
            "mean_shape": shape,
            "var_shape": shape,
            "epsilon": self.epsilon,
            "clip_obs": self.clip_obs,
        }


def _state(obj: Any) -> dict | None:
    return obj.state if isinstance(obj, Inert) and isinstance(obj.state, dict) else None


def _number(path: Path, state: dict, key: str, default: float | None = None) -> float:
    value = state.get(key, default)
    number = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
    out = float(value) if number and abs(value) < 1e300 else float("nan")
    if not (math.isfinite(out) and out >= 0):
        raise ArtifactError(f"{path}: VecNormalize {key} = {_brief(value)}; expected a finite number >= 0")
    return out


def _stat_array(path: Path, rms: dict, key: str) -> np.ndarray:
    arr = rms.get(key)
    if not isinstance(arr, np.ndarray) or arr.dtype.kind != "f" or arr.ndim != 1:
        got = f"{arr.dtype} {arr.shape}" if isinstance(arr, np.ndarray) else type(arr).__name__
        raise ArtifactError(f"{path}: obs_rms.{key} is {got}; expected a 1-d float array (a flat Box's statistics)")
    if not np.isfinite(arr).all():
        raise ArtifactError(f"{path}: obs_rms.{key} holds NaN or infinite values")
    return arr.astype(np.float64)


def read_vecnormalize(path: str | Path) -> ObsStatistics:
    """The observation statistics of SB3 VecNormalize file `path` (VecNormalize.save's pickle);
    ArtifactError naming the file for a missing, huge or damaged file, a pickle naming anything
    but the allowed names, an object other than a VecNormalize, or statistics that are not
    those of a flat Box (dict observations, non-finite or negative variances)."""
    path = Path(path)
    if not path.is_file():
        raise ArtifactError(f"{path}: no such file (expected SB3's VecNormalize statistics, e.g. vecnormalize.pkl)")
    size = path.stat().st_size
    if size > MAX_BYTES:
        raise ArtifactError(f"{path}: {size} bytes; a VecNormalize file of a flat Box is a few kB (refused unread)")
    top = restricted_loads(path.read_bytes(), path, "the pickle")
    state = _state(top)
    if state is None or top.name != VEC_NORMALIZE:
        got = top.name if isinstance(top, Inert) else type(top).__name__
        raise ArtifactError(f"{path}: holds {got or 'an object'}; expected a pickled {VEC_NORMALIZE}")
    norm_obs, norm_reward = state.get("norm_obs"), state.get("norm_reward", False)
    for key, flag in (("norm_obs", norm_obs), ("norm_reward", norm_reward)):
        if not isinstance(flag, (bool, np.bool_)):
            raise ArtifactError(f"{path}: VecNormalize {key} = {_brief(flag)}; expected true or false")
    epsilon = _number(path, state, "epsilon", 1e-8)
    clip_obs = _number(path, state, "clip_obs", 10.0)
    norm_obs, norm_reward = bool(norm_obs), bool(norm_reward)
    if not norm_obs:
        return ObsStatistics(False, None, None, epsilon, clip_obs, norm_reward)
    rms = _state(state.get("obs_rms"))
    if rms is None or state["obs_rms"].name != RUNNING_MEAN_STD:
        got = state.get("obs_rms")
        kind = got.name if isinstance(got, Inert) else type(got).__name__
        raise ArtifactError(
            f"{path}: obs_rms is {kind}; expected one RunningMeanStd (a flat Box observation, not a Dict)"
        )
    mean, var = _stat_array(path, rms, "mean"), _stat_array(path, rms, "var")
    if mean.shape != var.shape:
        raise ArtifactError(f"{path}: obs_rms.mean has shape {mean.shape}, obs_rms.var {var.shape}")
    if (var < 0).any() or not (var + epsilon > 0).all():
        raise ArtifactError(f"{path}: obs_rms.var + epsilon is not positive everywhere (var min {var.min():g})")
    return ObsStatistics(True, mean, var, epsilon, clip_obs, norm_reward)
