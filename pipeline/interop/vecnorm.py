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
numpy's array, dtype and scalar reconstruction (plain data, needed for the statistics); every
name of SB3, Gymnasium's or gym's spaces and numpy.random becomes an inert stand-in that
records the arguments and state the pickle gives it and runs nothing (their modules are not
even imported). Any other name (os.system, builtins.eval, ...) stops the read at once with one
line naming the file and the name, before anything it would call exists. A stack machine over
`pickletools.genops` would re-implement the memo and every opcode's stack effect to find the
same names, with more room for a mistake.
"""

from __future__ import annotations

import io
import pickle
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from pipeline.core.artifacts import ArtifactError

MAX_BYTES = 64 << 20  # a VecNormalize file of a flat Box is a few kB; refuse anything huge unread
VEC_NORMALIZE = "stable_baselines3.common.vec_env.vec_normalize.VecNormalize"
RUNNING_MEAN_STD = "stable_baselines3.common.running_mean_std.RunningMeanStd"
# names whose stand-in is inert: SB3's classes, the spaces a wrapper pickles, their generators
INERT_PREFIXES = ("stable_baselines3.", "gymnasium.spaces.", "gym.spaces.", "numpy.random.")


class _NdarrayName:
    """What the pickle gets for the name numpy.ndarray: only a token for `_reconstruct`'s first
    argument. Called itself it refuses: `ndarray(shape, object_dtype, buffer=...)` would build
    an array of object pointers from the pickle's raw bytes (a crash, not a refusal)."""

    def __new__(cls, *args: Any, **kwargs: Any) -> Any:
        raise pickle.UnpicklingError("numpy.ndarray called directly: statistics are rebuilt, never constructed")


def _plain(dtype: Any) -> np.dtype:
    """`dtype` as a numpy dtype, refused if it holds Python objects (statistics are numbers)."""
    d = dtype if isinstance(dtype, np.dtype) else np.dtype(dtype)
    if d.hasobject:
        raise pickle.UnpicklingError(f"an array or scalar of dtype {d} holds Python objects, not numbers")
    return d


def _numpy_rebuilders() -> dict[tuple[str, str], Any]:
    """numpy's own array, dtype and scalar rebuilders under the module names numpy 1 (numpy.core)
    and numpy 2 (numpy._core) pickle them with; taken from numpy's reductions, not imported by
    name, and wrapped: an array is rebuilt only as a plain ndarray, and nothing of object dtype
    is made from bytes (an object array's BUILD state must be a list of objects the pickle made
    through this same gate, which numpy enforces)."""
    reconstruct = np.zeros(1).__reduce__()[0]
    frombuffer = np.zeros(1).__reduce_ex__(5)[0]
    scalar = np.float64(1.0).__reduce__()[0]

    def rebuild(subtype: Any, shape: Any, dtype: Any) -> np.ndarray:
        if subtype is not _NdarrayName:
            raise pickle.UnpicklingError("an array rebuilt as another type than numpy.ndarray")
        return reconstruct(np.ndarray, shape, dtype)

    def from_buffer(buf: Any, dtype: Any, shape: Any, order: Any) -> np.ndarray:
        return frombuffer(buf, _plain(dtype), shape, order)

    def make_scalar(dtype: Any, *args: Any) -> Any:
        return scalar(_plain(dtype), *args)

    out: dict[tuple[str, str], Any] = {("numpy", "ndarray"): _NdarrayName, ("numpy", "dtype"): np.dtype}
    for core in ("numpy.core", "numpy._core"):
        out[(f"{core}.multiarray", "_reconstruct")] = rebuild
        out[(f"{core}.multiarray", "scalar")] = make_scalar
        out[(f"{core}.numeric", "_frombuffer")] = from_buffer
    return out


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


class _Refused(Exception):
    def __init__(self, module: str, name: str):
        super().__init__(f"{module}.{name}")


class _RestrictedUnpickler(pickle.Unpickler):
    _numpy = _numpy_rebuilders()

    def __init__(self, data: bytes):
        super().__init__(io.BytesIO(data))
        self._inert: dict[str, type[Inert]] = {}

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in self._numpy:
            return self._numpy[(module, name)]
        if module.startswith(INERT_PREFIXES) and name.isidentifier():
            key = f"{module}.{name}"
            if key not in self._inert:
                self._inert[key] = type(name, (Inert,), {"name": key})
            return self._inert[key]
        raise _Refused(module, name)


def restricted_loads(data: bytes, path: Path, what: str) -> Any:
    """Unpickle `data` (of file `path`, described as `what`) through the allow-list above;
    ArtifactError with one line naming the file and the first name refused, or the damage."""
    try:
        return _RestrictedUnpickler(data).load()
    except _Refused as exc:
        raise ArtifactError(
            f"{path}: {what} refers to {exc}, which a file of observation statistics does not need; refused "
            "unread (only numpy arrays and inert names of SB3, Gymnasium spaces and numpy.random are read)"
        ) from None
    except RecursionError:
        raise ArtifactError(f"{path}: {what} nests too deep to be a file of observation statistics") from None
    except (
        pickle.UnpicklingError,
        EOFError,
        ValueError,
        TypeError,
        AttributeError,
        KeyError,
        IndexError,
        MemoryError,
    ) as exc:
        first = str(exc).strip().splitlines()[0][:160] if str(exc).strip() else type(exc).__name__
        raise ArtifactError(f"{path}: {what} is not a readable pickle ({first})") from None


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
    try:
        out = float(value)
    except (TypeError, ValueError):
        out = float("nan")
    if isinstance(value, bool) or not (out >= 0):
        raise ArtifactError(f"{path}: VecNormalize {key} = {value!r}; expected a number >= 0")
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
    norm_obs = state.get("norm_obs")
    if not isinstance(norm_obs, (bool, np.bool_)):
        raise ArtifactError(f"{path}: VecNormalize norm_obs = {norm_obs!r}; expected true or false")
    epsilon = _number(path, state, "epsilon", 1e-8)
    clip_obs = _number(path, state, "clip_obs", 10.0)
    norm_reward = bool(state.get("norm_reward", False))
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
