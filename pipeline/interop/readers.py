"""Readers for specialists trained elsewhere: Stable-Baselines3 zips, CleanRL checkpoints,
TorchScript actors and torch.export programs (.pt2), each turned into a deterministic policy of this project (docs/import_export.md).

Nothing here imports SB3 or CleanRL, and nothing unpickles: an SB3 `model.zip` is read from its
`data` JSON (the algorithm, the spaces' shapes and bounds, the policy's keyword arguments) and
its `policy.pth` (loaded with weights_only=True); a CleanRL `.cleanrl_model` is a tuple of
state dicts, also loaded with weights_only=True. What only unpickling could read (a custom
features extractor, an activation given as a class we do not build, a file of pickled
objects) is refused with a message naming the file; so is anything that does not fit the env.

- SB3 TD3 and DDPG (`TD3Policy`): `actor.mu` is Linear/ReLU/.../Linear then tanh; SB3 rescales
  the [-1, 1] output to the action space's bounds outside the network.
- SB3 SAC (`SACPolicy`): the deterministic action is tanh(mu(latent_pi(obs))), rescaled the same
  way; log_std is not used. gSDE policies are refused (their mean is clipped and their noise is
  state-dependent: a different network).
- CleanRL TD3/DDPG (`fc1`, `fc2`, ..., `fc_mu`) and SAC (`fc_mean`, `fc_logstd` unused): tanh
  output times `action_scale` plus `action_bias`.

All of these are exactly `pipeline.core.nets.Actor` (ReLU MLP, tanh, centre + scale), so the
imported weights are copied into one and everything downstream reads them as it reads its own.
A TorchScript file becomes a `ScriptedActor` holding the file's bytes; a `.pt2` file of
`torch.export.save` an `ExportedActor` holding its bytes (the program's batch axis must be
exported as dynamic: the checks below run it on a batch of 4).

An MLP trained under SB3's `VecNormalize(norm_obs=True)` comes with the observation statistics
file SB3 saves beside it (pipeline.interop.vecnorm reads it without running its code); with
it, the actor becomes a `NormalizedActor`, which normalises raw observations as the policy saw
them. Two signs in an SB3 TD3/DDPG/SAC zip tell whether that is needed (docs/import_export.md):

- Without statistics: the scale of each input the networks saw in training. Adam's second
  moment of the critic's first-layer weights (critic.optimizer.pth, loaded with
  weights_only=True), averaged over the layer's units, grows with the square of each input's
  scale, so its square root per observation dim is the profile of input scales training saw (up
  to one factor). Under VecNormalize that profile is flat (every input about unit scale); on raw
  observations it follows the raw scales, which span orders of magnitude in MuJoCo (positions
  ~0.1, velocities ~10). `input_scale_warning` compares it with the raw scales of the
  observations collected (or handed in) and warns when it is much flatter than they are.
- With statistics: SB3's off-policy algorithms keep the last observation of training twice, as
  the policy saw it (`_last_obs`) and as the env gave it (`_last_original_obs`); under a
  VecNormalize both are of the same step, so the statistics must turn one into the other
  (`normalization_warnings`; without a VecNormalize the two are consecutive raw observations,
  so they say nothing there).
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import io
import json
import pickle
import pickletools
import re
import zipfile
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import nn

from pipeline.core.artifacts import ArtifactError, first_line
from pipeline.core.envs import EnvSpec
from pipeline.core.nets import Actor, ExportedActor, NormalizedActor, ScriptedActor
from pipeline.core.tscheck import check_torchscript
from pipeline.interop.vecnorm import ObsStatistics, read_vecnormalize, restricted_loads
from pipeline.params.import_specialists import IMPORT_FORMATS, NORMALIZABLE_FORMATS

FORMATS = IMPORT_FORMATS  # listed once, with the params model (pipeline/params/import_specialists.py)
SB3_POLICIES = {"TD3Policy": "td3", "SACPolicy": "sac"}  # DDPG saves a TD3Policy
# the builtins a pickle of plain settings may name (containers and numbers, no callables of code)
PLAIN_BUILTINS = frozenset(
    {"dict", "list", "tuple", "set", "frozenset", "int", "float", "bool", "str", "bytes", "complex"}
)


class ImportedPolicy(NamedTuple):
    actor: Actor | ScriptedActor  # eval mode, CPU
    # "mlp" (an Actor), "normalized_mlp" (a NormalizedActor), "torchscript" (a ScriptedActor) or
    # "torch_export" (an ExportedActor)
    architecture: str
    hidden_sizes: list[int]  # [] for TorchScript and torch.export programs
    source: dict[str, Any]  # format, algorithm, file, sha256, library version where known; normalize
    warnings: tuple[str, ...] = ()  # one line each: what makes the import likely wrong (the stage prints them)
    # per observation dim, the scale of the inputs the first layer saw in training, up to one
    # factor (SB3: from the critic's Adam state); None where the file does not tell
    input_scales: np.ndarray | None = None


class _Declared(NamedTuple):
    """What a file says of its env (None where it says nothing)."""

    obs_dim: int | None
    act_dim: int | None
    low: np.ndarray | None
    high: np.ndarray | None


def file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


MAX_MEMBER = 256 << 20  # bytes of one member of an SB3 zip (a policy of 256-unit MLPs is about 1 MB)


def _tensor_bytes(obj: Any) -> int:
    """The bytes the tensors in `obj` (nested dicts, lists, tuples of them) span, each counted
    as its shape says (an expanded view counts as what copying it would allocate)."""
    total, stack, seen = 0, [obj], set()
    while stack:
        item = stack.pop()
        if id(item) in seen:
            continue
        seen.add(id(item))
        if isinstance(item, torch.Tensor):
            total += item.numel() * item.element_size()
        elif isinstance(item, dict):
            stack.extend(item.values())
        elif isinstance(item, (list, tuple)):
            stack.extend(item)
    return total


def _weights_only(path: Path, data: bytes | None, what: str) -> Any:
    """torch.load(weights_only=True) of a file (or its bytes), unpickling refused with a clear line;
    so are tensors that span more bytes than the file holds (a size or stride the file chose: using
    them would allocate that much) and any other error of torch on damaged bytes."""
    if data is None:
        data = path.read_bytes()
    # the pickle checked within a budget before torch's own unpickler builds it (issue 57): declared
    # and inflated sizes, opcodes counted, dicts inert (torch.save writes TorchScript's zip layout)
    check_torchscript(data, path, "torch.save")
    try:
        obj = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        raise ArtifactError(
            f"{path}: {what} holds Python objects that only unpickling their code could read ({first_line(exc)}); "
            "refused: save the weights as a state dict (or the actor as TorchScript) and import that"
        ) from None
    except Exception as exc:  # damaged bytes make torch.load raise nearly any built-in error
        raise ArtifactError(f"{path}: {what} is not a readable torch file ({first_line(exc)})") from None
    size = len(data)
    spans = _tensor_bytes(obj)
    if spans > size:
        raise ArtifactError(
            f"{path}: {what} declares tensors of {spans} bytes in {size} bytes (a tensor's size or stride is "
            "damaged or crafted); refused before using them"
        )
    return obj


def mlp_actor(path: Path, layers: list[tuple[torch.Tensor, torch.Tensor]], low, high) -> Actor:
    """An `Actor` holding these (weight (out, in), bias (out,)) Linear layers, ReLU between them."""
    if not layers:
        raise ArtifactError(f"{path}: no Linear layers found for the actor")
    for i, (w, b) in enumerate(layers):
        if not isinstance(w, torch.Tensor) or not isinstance(b, torch.Tensor):
            raise ArtifactError(f"{path}: layer {i} has a weight or bias that is not a tensor")
        if w.ndim != 2 or b.shape != (w.shape[0],):
            raise ArtifactError(f"{path}: layer {i} has weight {tuple(w.shape)} and bias {tuple(b.shape)}")
        if i and w.shape[1] != layers[i - 1][0].shape[0]:
            raise ArtifactError(
                f"{path}: layer {i} takes {w.shape[1]} inputs, layer {i - 1} gives {layers[i - 1][0].shape[0]}"
            )
    obs_dim, act_dim = layers[0][0].shape[1], layers[-1][0].shape[0]
    hidden = [w.shape[0] for w, _ in layers[:-1]]
    actor = Actor(obs_dim, act_dim, hidden, low, high)
    linears = [m for m in actor.net if isinstance(m, nn.Linear)]
    with torch.no_grad():
        for lin, (w, b) in zip(linears, layers):
            lin.weight.copy_(w.float())
            lin.bias.copy_(b.float())
    return actor.eval()


def _indexed_layers(path: Path, state: dict[str, torch.Tensor], prefix: str) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """The Linear layers `prefix`0, `prefix`2, ... of an nn.Sequential of Linear and ReLU."""
    found = sorted({int(m.group(1)) for k in state if (m := re.fullmatch(re.escape(prefix) + r"(\d+)\.weight", k))})
    if found != list(range(0, 2 * len(found), 2)):
        raise ArtifactError(
            f"{path}: the layers of {prefix.rstrip('.')} are {found}; expected Linear layers 0, 2, 4, ... "
            "with one activation between them (an SB3 MLP)"
        )
    lacking = [f"{prefix}{i}.bias" for i in found if f"{prefix}{i}.bias" not in state]
    if not found or lacking:
        raise ArtifactError(
            f"{path}: no layers {prefix}0, {prefix}2, ... with weights and biases ({lacking[:2]} missing)"
        )
    return [(state[f"{prefix}{i}.weight"], state[f"{prefix}{i}.bias"]) for i in found]


def _flat_dim(path: Path, space: dict, what: str) -> int:
    """The size of a flat Box as an SB3 zip's `data` declares it (`_shape`, a list of one int)."""
    shape = space.get("_shape")
    if type(shape) is not list or len(shape) != 1 or type(shape[0]) is not int or not 0 < shape[0] <= 1 << 20:
        shown = str(shape)[:60] if type(shape) is list else type(shape).__name__
        raise ArtifactError(
            f"{path}: {what} space is {str(space[':type:'])[:80]} of shape {shown}; expected a flat Box"
        )
    return shape[0]


# -- Stable-Baselines3 --------------------------------------------------------------------------


# A serialized SB3 entry (a space, policy_kwargs) runs a few hundred opcodes; its opcodes are
# streamed and counted, never listed (issue 57: listing them built ~900 MiB from an 11 KB zip).
MAX_ENTRY_OPCODES = 100_000
MAX_ENTRY_STRINGS = 10_000


def _entry_ops(encoded: str):
    """The opcodes of a serialized entry, one at a time, at most MAX_ENTRY_OPCODES (ValueError past it)."""
    for count, op in enumerate(pickletools.genops(base64.b64decode(encoded)), 1):
        if count > MAX_ENTRY_OPCODES:
            raise ValueError(f"more than {MAX_ENTRY_OPCODES} pickle opcodes")
        yield op


def _pickle_strings(encoded: str) -> list[str]:
    """The string constants of a serialized SB3 entry (class names of a class pickled by value
    among them), at most MAX_ENTRY_STRINGS; [] for an unreadable or oversized entry."""
    out: list[str] = []
    try:
        for _, arg, _ in _entry_ops(encoded):
            if isinstance(arg, str):
                out.append(arg[:200])
                if len(out) >= MAX_ENTRY_STRINGS:
                    break
    except (binascii.Error, ValueError, pickle.PickleError, EOFError, MemoryError, RecursionError):
        return []
    return out


def _pickle_globals(path: Path, key: str, encoded: str) -> list[tuple[str, str]]:
    """The (module, name) pairs a serialized SB3 entry refers to, read from its pickle opcodes
    without running them (pickletools only decodes them, one at a time)."""
    out: list[tuple[str, str]] = []
    last: list[str] = []  # the two latest strings (STACK_GLOBAL takes its module and name from them)
    try:
        for op, arg, _ in _entry_ops(encoded):
            if op.name in ("SHORT_BINUNICODE", "BINUNICODE", "UNICODE", "BINUNICODE8"):
                last = [last[-1], arg] if last else [arg]
            elif op.name == "STACK_GLOBAL" and len(last) == 2:
                out.append((last[0], last[1]))
            elif op.name in ("GLOBAL", "INST"):
                module, name = str(arg).split(" ", 1)
                out.append((module, name))
            if len(out) > MAX_ENTRY_STRINGS:
                raise ValueError(f"more than {MAX_ENTRY_STRINGS} names")
    except (binascii.Error, ValueError, pickle.PickleError, EOFError, MemoryError, RecursionError) as exc:
        raise ArtifactError(f"{path}: data[{key!r}] is not a readable serialized entry ({exc})") from None
    return out


def _space(path: Path, data: dict, key: str) -> dict:
    entry = data.get(key)
    if not isinstance(entry, dict) or ":type:" not in entry:
        raise ArtifactError(f"{path}: data has no readable {key!r}; expected an SB3 model.zip")
    return entry


def _parse_bounds(text: Any) -> np.ndarray | None:
    """An SB3 space's `low`/`high` as printed (numpy's repr, e.g. '[-1. -1.]'); None if elided."""
    if not isinstance(text, str) or "..." in text:
        return None
    try:
        return np.array(text.replace("[", " ").replace("]", " ").split(), dtype=np.float64)
    except ValueError:
        return None


def _serialized_array(path: Path, data: dict, key: str) -> np.ndarray | None:
    """The float array a serialized SB3 entry holds (read through the restricted unpickler of
    pipeline.interop.vecnorm); None where there is none or it holds anything else. A pickle that
    unpickler refuses (a name of code, a dtype that is not a plain number, an array bigger than
    the entry, damage) refuses the file with its one line: a zip SB3 wrote never holds one."""
    entry = data.get(key)
    if not isinstance(entry, dict) or not isinstance(entry.get(":serialized:"), str):
        return None
    try:
        raw = base64.b64decode(entry[":serialized:"])
    except (binascii.Error, ValueError) as exc:
        raise ArtifactError(f"{path}: data[{key!r}] is not base64 ({exc})") from None
    value = restricted_loads(raw, path, f"data[{key!r}]")
    return value if isinstance(value, np.ndarray) and value.dtype.kind == "f" else None


def _last_observations(path: Path, data: dict) -> tuple[np.ndarray, np.ndarray] | None:
    """(the last observation as the policy saw it, as the env gave it), saved by SB3's
    off-policy algorithms as `_last_obs` and `_last_original_obs`; None where either is missing
    (a model saved before learning) or they are not arrays of one shape."""
    seen, raw = _serialized_array(path, data, "_last_obs"), _serialized_array(path, data, "_last_original_obs")
    if seen is None or raw is None or seen.shape != raw.shape:
        return None
    return seen.astype(np.float64), raw.astype(np.float64)


def _input_scales(path: Path, optimizer_bytes: bytes | None, obs_dim: int, act_dim: int) -> np.ndarray | None:
    """sqrt of Adam's exp_avg_sq of the critic's first-layer weight, averaged over its units, for
    each observation input (see the module's docstring); None where the zip has no such state."""
    if optimizer_bytes is None:
        return None
    try:
        state = _weights_only(path, optimizer_bytes, "critic.optimizer.pth")
        first = state["state"][0]["exp_avg_sq"]  # the first parameter: qf0's first Linear weight
    except (ArtifactError, KeyError, IndexError, TypeError):
        return None
    if not isinstance(first, torch.Tensor) or first.ndim != 2 or first.shape[1] != obs_dim + act_dim:
        return None
    return first.double().mean(dim=0).sqrt().numpy()[:obs_dim]


def read_sb3(path: Path) -> tuple[Actor, _Declared, dict[str, Any]]:
    try:
        zf = zipfile.ZipFile(path)
    except Exception as exc:  # a damaged central directory raises BadZipFile, ValueError, OverflowError, ...
        raise ArtifactError(
            f"{path}: not a readable zip ({first_line(exc)}); expected a Stable-Baselines3 model.zip"
        ) from None
    with zf:
        names = set(zf.namelist())
        lacking = [n for n in ("data", "policy.pth") if n not in names]
        if lacking:
            raise ArtifactError(
                f"{path}: zip has no {lacking}; expected a Stable-Baselines3 model.zip (data, policy.pth)"
            )
        wanted = ["data", "policy.pth", "critic.optimizer.pth", "_stable_baselines3_version"]
        big = [(n, zf.getinfo(n).file_size) for n in wanted if n in names and zf.getinfo(n).file_size > MAX_MEMBER]
        if big:
            raise ArtifactError(f"{path}: zip member {big[0][0]} declares {big[0][1]} bytes; at most {MAX_MEMBER} read")
        try:
            raw = zf.read("data")
            policy_bytes = zf.read("policy.pth")
            critic_opt = zf.read("critic.optimizer.pth") if "critic.optimizer.pth" in names else None
            version = (
                zf.read("_stable_baselines3_version").decode(errors="replace").strip()[:80]
                if "_stable_baselines3_version" in names
                else None
            )
        except Exception as exc:  # zlib.error, BadZipFile (a bad CRC), NotImplementedError (a compression method), ...
            raise ArtifactError(f"{path}: zip is damaged ({first_line(exc)})") from None
        try:
            data = json.loads(raw)
        except (ValueError, RecursionError) as exc:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
            raise ArtifactError(
                f"{path}: its 'data' entry is not JSON ({first_line(exc)}); expected a Stable-Baselines3 model.zip"
            ) from None
    if not isinstance(data, dict):
        raise ArtifactError(f"{path}: its 'data' entry is not a JSON object; expected a Stable-Baselines3 model.zip")
    act_space, obs_space = _space(path, data, "action_space"), _space(path, data, "observation_space")
    if "spaces.box.Box" not in str(act_space[":type:"]):
        raise ArtifactError(
            f"{path}: action space is {act_space[':type:']}, not a continuous Box; MAPEX extracts continuous-control "
            "policies (SB3 TD3, DDPG or SAC)"
        )
    if "spaces.box.Box" not in str(obs_space[":type:"]):
        raise ArtifactError(f"{path}: observation space is {str(obs_space[':type:'])[:80]}; expected a flat Box")
    obs_dim, act_dim = _flat_dim(path, obs_space, "observation"), _flat_dim(path, act_space, "action")
    policy = data.get("policy_class")
    classes = (
        _pickle_globals(path, "policy_class", policy[":serialized:"])
        if isinstance(policy, dict) and isinstance(policy.get(":serialized:"), str)
        else []
    )
    cls = next((name for module, name in classes if module.startswith("stable_baselines3.")), None)
    if cls not in SB3_POLICIES:
        raise ArtifactError(
            f"{path}: policy class {cls or 'unknown'}; expected one of {sorted(SB3_POLICIES)} "
            "(SB3 TD3, DDPG or SAC with an MlpPolicy)"
        )
    algorithm = SB3_POLICIES[cls]
    kwargs = data.get("policy_kwargs") or {}
    if isinstance(kwargs, dict) and ":serialized:" in kwargs:
        if not isinstance(kwargs[":serialized:"], str):
            raise ArtifactError(f"{path}: data['policy_kwargs'] is not a serialized entry")
        refs = [
            (m, n)
            for m, n in _pickle_globals(path, "policy_kwargs", kwargs[":serialized:"])
            if not (m == "builtins" and n in PLAIN_BUILTINS)  # builtins.exec, eval, getattr ... are code
        ]
        activations = [n for m, n in refs if m == "torch.nn.modules.activation"]
        if any(a != "ReLU" for a in activations):
            raise ArtifactError(
                f"{path}: policy_kwargs set activation_fn {activations}; this reader builds ReLU networks (SB3's default)"
            )
        other = sorted({f"{m}.{n}" for m, n in refs if m != "torch.nn.modules.activation"})
        if other:
            classes = sorted({t for t in _pickle_strings(kwargs[":serialized:"]) if re.fullmatch(r"[A-Z]\w+", t)})
            named = f"classes {', '.join(classes)}; " if classes else ""
            raise ArtifactError(
                f"{path}: policy_kwargs refer to code ({named}{', '.join(other)[:200]}); reading them would need "
                "unpickling, refused: import the actor as TorchScript instead"
            )
    elif isinstance(kwargs, dict) and kwargs.get("use_sde"):
        raise ArtifactError(f"{path}: a gSDE policy (use_sde: true); only SAC without gSDE is read")
    if data.get("use_sde"):
        raise ArtifactError(f"{path}: a gSDE policy (use_sde: true); only SAC without gSDE is read")
    state = _weights_only(path, policy_bytes, "policy.pth")
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise ArtifactError(f"{path}: policy.pth is not a state dict of tensors")
    if algorithm == "td3":
        layers = _indexed_layers(path, state, "actor.mu.")
    else:
        if "actor.mu.weight" not in state or "actor.mu.bias" not in state:
            raise ArtifactError(f"{path}: SAC policy.pth has no actor.mu.weight and actor.mu.bias")
        layers = [*_indexed_layers(path, state, "actor.latent_pi."), (state["actor.mu.weight"], state["actor.mu.bias"])]
    low, high = _parse_bounds(act_space.get("low")), _parse_bounds(act_space.get("high"))
    actor = mlp_actor(
        path, layers, low if low is not None else -np.ones(act_dim), high if high is not None else np.ones(act_dim)
    )
    declared = _Declared(obs_dim, act_dim, low, high)
    info = {"algorithm": algorithm, "library": "stable-baselines3", "library_version": version}
    scales = _input_scales(path, critic_opt, declared.obs_dim, declared.act_dim)
    return actor, declared, info | {"last_obs": _last_observations(path, data), "input_scales": scales}


# -- CleanRL ------------------------------------------------------------------------------------


def read_cleanrl(path: Path) -> tuple[Actor, _Declared, dict[str, Any]]:
    obj = _weights_only(path, None, "the checkpoint")
    actor_state = obj[0] if isinstance(obj, (tuple, list)) and obj else obj
    if not isinstance(actor_state, dict) or "fc1.weight" not in actor_state:
        raise ArtifactError(
            f"{path}: not a CleanRL checkpoint (expected a tuple of state dicts, the actor's first, with fc1, fc2, "
            "fc_mu or fc_mean, action_scale and action_bias)"
        )
    head = "fc_mu" if "fc_mu.weight" in actor_state else "fc_mean" if "fc_mean.weight" in actor_state else None
    if head is None or "action_scale" not in actor_state or "action_bias" not in actor_state:
        raise ArtifactError(
            f"{path}: CleanRL actor has keys {sorted(actor_state)[:8]}...; expected fc_mu (TD3, DDPG) or fc_mean (SAC) "
            "with action_scale and action_bias"
        )
    hidden = sorted(int(m.group(1)) for k in actor_state if (m := re.fullmatch(r"fc(\d+)\.weight", k)))
    if hidden != list(range(1, len(hidden) + 1)):
        raise ArtifactError(f"{path}: CleanRL actor layers fc{hidden}; expected fc1, fc2, ... in order")
    needed = [f"fc{i}.bias" for i in hidden] + [f"{head}.bias"]
    lacking = [k for k in needed if k not in actor_state]
    if lacking or not all(isinstance(actor_state[k], torch.Tensor) for k in ("action_scale", "action_bias")):
        raise ArtifactError(f"{path}: CleanRL actor lacks {lacking[:3] or 'tensors action_scale, action_bias'}")
    layers = [(actor_state[f"fc{i}.weight"], actor_state[f"fc{i}.bias"]) for i in hidden]
    layers.append((actor_state[f"{head}.weight"], actor_state[f"{head}.bias"]))
    scale = actor_state["action_scale"].double().flatten().numpy()
    bias = actor_state["action_bias"].double().flatten().numpy()
    actor = mlp_actor(path, layers, bias - scale, bias + scale)
    declared = _Declared(layers[0][0].shape[1], layers[-1][0].shape[0], bias - scale, bias + scale)
    algorithm = "sac" if head == "fc_mean" else "td3"  # DDPG's actor is TD3's
    return actor, declared, {"algorithm": algorithm, "library": "cleanrl", "library_version": None}


# -- TorchScript --------------------------------------------------------------------------------


def read_torchscript(path: Path, spec: EnvSpec) -> tuple[ScriptedActor, _Declared, dict[str, Any]]:
    data = path.read_bytes()
    check_torchscript(data, path)  # tensors that fit their records: torch.jit.load trusts the pickles for that
    try:
        actor = ScriptedActor.from_bytes(data, spec.action_low, spec.action_high)
    except Exception as exc:  # torch.jit.load raises many kinds on damaged bytes
        raise ArtifactError(f"{path}: not a TorchScript file torch.jit.load can read ({first_line(exc)})") from None
    return (
        actor.eval(),
        _Declared(None, None, None, None),
        {"algorithm": None, "library": "torchscript", "library_version": None},
    )


def read_torch_export(path: Path, spec: EnvSpec) -> tuple[ExportedActor, _Declared, dict[str, Any]]:
    data = path.read_bytes()
    try:
        actor = ExportedActor.from_bytes(data, spec.action_low, spec.action_high)
    except ArtifactError as exc:  # pt2check refused the archive before torch.export.load saw it
        raise ArtifactError(f"{path}: {exc}") from None
    except Exception as exc:  # torch.export.load raises many kinds on a file that is not a program
        raise ArtifactError(
            f"{path}: not a torch.export program torch.export.load can read ({first_line(exc)}); expected a .pt2 file "
            "of torch.export.save"
        ) from None
    return (
        actor.eval(),
        _Declared(None, None, None, None),
        {"algorithm": None, "library": "torch.export", "library_version": None},
    )


# -- checks against the env ---------------------------------------------------------------------


def _check_env(path: Path, actor, declared: _Declared, spec: EnvSpec) -> None:
    """The policy fits env `spec`: its declared dims and bounds match, and on a probe batch it
    maps (B, obs_dim) observations to finite (B, act_dim) actions inside the bounds."""
    env = f"env {spec.env_id}"
    if declared.obs_dim is not None and declared.obs_dim != spec.obs_dim:
        raise ArtifactError(
            f"{path}: a policy for {declared.obs_dim}-d observations; {env} has {spec.obs_dim} (a model of another env?)"
        )
    if declared.act_dim is not None and declared.act_dim != spec.act_dim:
        raise ArtifactError(
            f"{path}: a policy for {declared.act_dim}-d actions; {env} has {spec.act_dim} (a model of another env?)"
        )
    low, high = np.array(spec.action_low), np.array(spec.action_high)
    for name, got, want in (("low", declared.low, low), ("high", declared.high, high)):
        if got is not None and (got.shape != want.shape or not np.allclose(got, want, rtol=1e-5, atol=1e-6)):
            raise ArtifactError(f"{path}: action bounds {name} = {got.tolist()}; {env} has {want.tolist()}")
    probe = torch.linspace(-1.0, 1.0, 4 * spec.obs_dim).reshape(4, spec.obs_dim)
    try:
        with torch.no_grad():
            out = actor(probe)
    except Exception as exc:  # a user's TorchScript may raise anything on the wrong input
        raise ArtifactError(
            f"{path}: the policy fails on a batch of {spec.obs_dim}-d observations of {env} ({str(exc).strip().splitlines()[0][:160]})"
        ) from None
    if not isinstance(out, torch.Tensor) or tuple(out.shape) != (4, spec.act_dim):
        shape = tuple(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
        raise ArtifactError(
            f"{path}: the policy maps a (4, {spec.obs_dim}) batch to {shape}; expected (4, {spec.act_dim})"
        )
    if not torch.isfinite(out).all():
        raise ArtifactError(f"{path}: the policy returns NaN or infinite actions on a probe batch")
    slack = 1e-5 * (high - low)
    if (out.numpy() < low - slack).any() or (out.numpy() > high + slack).any():
        raise ArtifactError(
            f"{path}: the policy returns actions outside {env}'s bounds [{low.min()}, {high.max()}] "
            "(expected actions already rescaled to the env's bounds)"
        )


# -- observation statistics ---------------------------------------------------------------------

NORMALIZABLE = NORMALIZABLE_FORMATS  # the formats read into an `Actor`, which statistics can precede


def normalized(path: Path, actor: Actor, stats: ObsStatistics, spec: EnvSpec) -> Actor:
    """`actor` preceded by the statistics (a `NormalizedActor` with its weights), or `actor`
    itself where they say the policy saw raw observations (norm_obs false)."""
    if not stats.norm_obs:
        return actor
    if stats.mean.shape != (spec.obs_dim,):
        raise ArtifactError(
            f"{path}: statistics of {stats.mean.shape[0]}-d observations; env {spec.env_id} has {spec.obs_dim} "
            "(the statistics of another env?)"
        )
    hidden = [m.out_features for m in actor.net if isinstance(m, nn.Linear)][:-1]
    low, high = (actor.centre - actor.scale), (actor.centre + actor.scale)
    out = NormalizedActor(spec.obs_dim, spec.act_dim, hidden, low, high, stats.mean, stats.std, stats.clip_obs)
    out.load_state_dict(actor.state_dict() | {k: v for k, v in out.state_dict().items() if k.startswith("obs_")})
    return out.eval()


def normalization_warnings(
    path: Path, stats_path: Path, stats: ObsStatistics, last: tuple[np.ndarray, np.ndarray] | None
) -> list[str]:
    """A line if statistics that normalise (norm_obs true) do not turn the model's last raw
    observation into the normalised one it saw (SB3's `_last_original_obs`, `_last_obs`)."""
    if last is None or not stats.norm_obs:
        return []
    seen, raw = last
    gap = float(np.abs(stats.normalize(raw).astype(np.float32) - seen).max())
    if gap <= 1e-4:
        return []
    return [
        f"{path}: warning: {stats_path} does not turn the model's last raw observation into the normalised one it "
        f"saw (differs by up to {gap:.3g}): statistics of another model, or of another point of its training?"
    ]


FLATTER = 0.5  # warn when the profile of input scales training saw is this much flatter than the raw one


def input_scale_warning(path: Path, input_scales: np.ndarray | None, obs: np.ndarray, normalized: bool) -> str | None:
    """A line if the policy in `path` was likely trained on normalised observations and is
    imported without statistics that normalise (`normalized` false): the spread (std over observation dims) of the
    log input scales its training saw is under FLATTER times their spread relative to the raw
    scales of `obs` (N, obs_dim), the observations it was collected (or handed in) with.
    None when statistics normalise, when the file gives no input scales (CleanRL, TorchScript,
    torch.export) or when fewer than 2 dims have non-zero scales on both sides."""
    if input_scales is None or normalized or len(obs) == 0:
        return None
    raw = np.sqrt(np.mean(np.square(obs.astype(np.float64)), axis=0))
    keep = (input_scales > 0) & (raw > 0)
    if keep.sum() < 2:
        return None
    seen = np.log(input_scales[keep])
    flat, versus_raw = float(np.std(seen)), float(np.std(seen - np.log(raw[keep])))
    if not flat < FLATTER * versus_raw:
        return None
    return (
        f"{path}: warning: likely trained on normalised observations (the inputs its training saw were all of "
        f"about one scale: log-scale spread {flat:.2f} over the observation dims, against {versus_raw:.2f} relative "
        "to the raw observations collected); imported without statistics it acts on raw observations it never saw "
        "and behaves wrongly: name its vecnormalize.pkl in import_specialists.policies[].normalize"
    )


def read_policy(path: str | Path, fmt: str, spec: EnvSpec, normalize: str | Path | None = None) -> ImportedPolicy:
    """`_read_policy`, with what a reader of outside bytes can still raise past its own checks
    (MemoryError under a memory limit, RecursionError on deep nesting) as the one-line refusal
    naming the file, never a traceback (docs/trust.md)."""
    try:
        return _read_policy(path, fmt, spec, normalize)
    except MemoryError:
        raise ArtifactError(f"{path}: refused: reading it needed more memory than this process may use") from None
    except RecursionError:
        raise ArtifactError(f"{path}: refused: it nests deeper than a {fmt} model does") from None


def _read_policy(path: str | Path, fmt: str, spec: EnvSpec, normalize: str | Path | None = None) -> ImportedPolicy:
    """Read a policy trained elsewhere (`fmt` one of FORMATS) for env `spec`, with the
    observation statistics of SB3 VecNormalize file `normalize` (None: none) baked in; raises
    ArtifactError naming the file for a missing or unreadable file, a format it is not, a
    policy that only unpickling could read, discrete actions, dims and bounds of another env,
    statistics refused by pipeline.interop.vecnorm or for another env, or statistics for a
    TorchScript or torch.export policy (whose input transform is its own code)."""
    path = Path(path)
    if fmt not in FORMATS:
        raise ArtifactError(f"{path}: format {fmt!r}; expected one of {list(FORMATS)}")
    if not path.is_file():
        raise ArtifactError(f"{path}: no such file (expected a {fmt} model)")
    if normalize is not None and fmt not in NORMALIZABLE:
        raise ArtifactError(
            f"{normalize}: observation statistics for a {fmt} policy; normalise inside the saved module instead "
            f"(statistics are read for {', '.join(NORMALIZABLE)} models)"
        )
    stats = read_vecnormalize(normalize) if normalize is not None else None
    if fmt == "torchscript":
        actor, declared, source = read_torchscript(path, spec)
    elif fmt == "torch_export":
        actor, declared, source = read_torch_export(path, spec)
    else:
        actor, declared, source = (read_sb3 if fmt == "sb3" else read_cleanrl)(path)
    last, scales = source.pop("last_obs", None), source.pop("input_scales", None)
    if stats is not None:
        actor = normalized(Path(normalize), actor, stats, spec)
    _check_env(path, actor, declared, spec)
    architecture = (
        "torch_export"
        if isinstance(actor, ExportedActor)
        else "torchscript"
        if isinstance(actor, ScriptedActor)
        else "normalized_mlp"
        if isinstance(actor, NormalizedActor)
        else "mlp"
    )
    hidden = (
        [] if not isinstance(actor, Actor) else [m.out_features for m in actor.net if isinstance(m, nn.Linear)][:-1]
    )
    source = {"format": fmt, **source, "file": path.name, "sha256": file_sha256(path)}
    if stats is not None:
        source["normalize"] = {"file": str(normalize), "sha256": file_sha256(Path(normalize)), **stats.record()}
    warnings = normalization_warnings(path, Path(normalize), stats, last) if stats is not None else []
    return ImportedPolicy(actor, architecture, hidden, source, tuple(warnings), scales)
